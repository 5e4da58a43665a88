"""Issue 37 (hostile round 3): the generated harness reads exactly what ``thetahat estimate``
reads (docs/bad-input.md, "The rules of a record").

The same hostile CSV goes to ``thetahat estimate`` and to the harness built by ``thetahat
codegen`` for prop1 (and for two_inertia: two inputs' worth of names, two outputs): both
accept or both refuse, and when both accept, the estimates agree to AGREE_RTOL. Each case
also states which it should be, so the test cannot pass by both readers drifting together.

AGREE_RTOL = 1e-9 relative to each column's largest |value|: the conformance matrix's bound
for the C against the Python observer (rounding only: measured below 1e-13 here).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.codegen.loader import find_compiler
from thetahat.modelfile import load_model
from thetahat.modelfile.study import simulate_model

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler (cc or $CC)")

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
AGREE_RTOL = 1e-9
DT = 0.01
N = 60


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """model name → (model file, harness, t, u (N, m), y (N, r))."""
    out = {}
    for name in ("prop1", "two_inertia"):
        folder = tmp_path_factory.mktemp(name)
        model = EXAMPLES / f"{name}.toml"
        assert main(["codegen", str(model), "--dt", repr(DT), "-o", str(folder)]) == 0
        make = subprocess.run(["make", "-C", str(folder)], capture_output=True, text=True)
        assert make.returncode == 0, make.stderr
        run = simulate_model(load_model(model), 1, t_end=(N - 1) * DT * 1.5)
        t = np.arange(N) * DT
        u = np.stack([np.interp(t, run.t, c) for c in run.u.reshape(run.t.size, -1).T], 1)
        y = np.stack([np.interp(t, run.t, c) for c in run.y.reshape(run.t.size, -1).T], 1)
        out[name] = (model, folder / name, t, u, y)
    return out


def rows(t, u, y, sep: str = ",", fmt=repr) -> list[list[str]]:
    return [[fmt(float(a)) for a in (tt, *uu, *yy)] for tt, uu, yy in zip(t, u, y)]


def text(header: list[str], body: list[list[str]], sep: str = ",", end: str = "\n") -> str:
    return end.join(sep.join(r) for r in [header, *body]) + end


def base(d, sep=",", end="\n") -> str:
    _, _, t, u, y = d
    return text(["t", "u", "y"], rows(t, u, y), sep, end)


def decimal_comma(d, sep) -> bytes:
    _, _, t, u, y = d
    body = rows(t, u, y, fmt=lambda a: repr(a).replace(".", ","))
    return text(["t", "u", "y"], body, sep).encode()


def with_cell(d, row: int, col: int, cell: str, header=("t", "u", "y")) -> bytes:
    _, _, t, u, y = d
    body = rows(t, u, y)
    body[row][col] = cell
    return text(list(header), body).encode()


def with_column(d, name: str, cells, at: int = 3) -> bytes:
    _, _, t, u, y = d
    body = rows(t, u, y)
    header = ["t", "u", "y"]
    header.insert(at, name)
    for r, c in zip(body, cells):
        r.insert(at, c)
    return text(header, body).encode()


def lines(d) -> list[str]:
    return base(d).splitlines()


#: (case, the file's bytes from the data, "accept" or "refuse").
CASES = [
    ("plain", lambda d: base(d).encode(), "accept"),
    ("byte-order mark", lambda d: b"\xef\xbb\xbf" + base(d).encode(), "accept"),
    ("CRLF", lambda d: base(d, end="\r\n").encode(), "accept"),
    ("CR only", lambda d: base(d, end="\r").encode(), "accept"),
    ("semicolons, decimal commas", lambda d: decimal_comma(d, ";"), "accept"),
    ("tabs, decimal commas", lambda d: decimal_comma(d, "\t"), "accept"),
    ("tabs, decimal points", lambda d: base(d, sep="\t").encode(), "accept"),
    ("semicolons, both decimal marks",
     lambda d: decimal_comma(d, ";").replace(b"0,0", b"0.0", 1), "refuse"),
    ("NUL in y", lambda d: with_cell(d, 3, 2, "0.5\x00"), "refuse"),
    ("NUL alone in y", lambda d: with_cell(d, 3, 2, "\x00"), "refuse"),
    ("NUL in an ignored column", lambda d: with_column(d, "note", ["a\x00b"] * N), "accept"),
    ("NUL in the header", lambda d: with_cell(d, 0, 0, "0", header=("t", "u", "y\x00")),
     "refuse"),
    ("y twice", lambda d: with_column(d, "y", rows(*d[2:])[0][2:3] * N), "refuse"),
    ("u twice", lambda d: with_column(d, "u", ["0"] * N), "refuse"),
    ("y and y1", lambda d: with_column(d, "y1", ["0"] * N), "refuse"),
    ("digit separator", lambda d: with_cell(d, 5, 1, "1_000"), "refuse"),
    ("text", lambda d: with_cell(d, 5, 2, "abc"), "refuse"),
    ("boolean", lambda d: with_cell(d, 5, 1, "True"), "refuse"),
    ("date in t", lambda d: with_cell(d, 0, 0, "2024-01-01"), "refuse"),
    ("hexadecimal", lambda d: with_cell(d, 5, 2, "0x1p-2"), "refuse"),
    ("nan(1)", lambda d: with_cell(d, 5, 2, "nan(1)"), "refuse"),
    ("full-width digit", lambda d: with_cell(d, 5, 1, "\uff11"), "refuse"),
    ("Arabic-Indic digit", lambda d: with_cell(d, 5, 1, "\u0661"), "refuse"),
    ("two decimal points", lambda d: with_cell(d, 5, 1, "1.2.3"), "refuse"),
    ("a lone exponent", lambda d: with_cell(d, 5, 1, "1e"), "refuse"),
    ("no-break spaces", lambda d: with_cell(d, 5, 1, "\u00a00.25\u3000"), "accept"),
    ("vertical tab, form feed", lambda d: with_cell(d, 5, 1, "\x0b0.25\x0c"), "accept"),
    ("+inf in u", lambda d: with_cell(d, 5, 1, "+inf"), "refuse"),
    ("Infinity in y", lambda d: with_cell(d, 5, 2, "Infinity"), "refuse"),
    ("1e999 in y", lambda d: with_cell(d, 5, 2, "1e999"), "refuse"),
    ("1e-400 in y", lambda d: with_cell(d, 5, 2, "1e-400"), "accept"),
    ("exact 500-digit number", lambda d: with_cell(d, 5, 1, "0." + "0" * 498 + "1"), "accept"),
    ("signs and exponents", lambda d: with_cell(d, 5, 1, "+2.5E-01"), "accept"),
    ("NaN in y (nan_policy raise)", lambda d: with_cell(d, 5, 2, "NaN"), "refuse"),
    ("N/A in y", lambda d: with_cell(d, 5, 2, "N/A"), "refuse"),
    ("empty t", lambda d: with_cell(d, 5, 0, ""), "refuse"),
    ("na in u", lambda d: with_cell(d, 5, 1, "na"), "refuse"),
    ("quoted cells", lambda d: "".join(f'"{line.replace(",", chr(34) + "," + chr(34))}"\n'
                                       for line in lines(d)).encode(), "accept"),
    ("quoted header with spaces", lambda d: ('"t" ,\t"u", "y" \n' + "\n".join(lines(d)[1:])
                                             + "\n").encode(), "refuse"),
    ("quoted, padded header", lambda d: ('  t ,"u",y\t\n' + "\n".join(lines(d)[1:])
                                         + "\n").encode(), "accept"),
    ("quote inside a cell", lambda d: with_cell(d, 5, 2, 'x"1"'), "refuse"),
    ("space before a quote", lambda d: with_cell(d, 5, 2, ' "0.5"'), "refuse"),
    ("text after the closing quote", lambda d: with_cell(d, 5, 2, '"0.5"x'), "refuse"),
    ("doubled quote", lambda d: with_cell(d, 5, 2, '"0.5"""'), "refuse"),
    ("blank lines and empty rows",
     lambda d: ("\n \n" + lines(d)[0] + "\n\n,,\n" + '""\n' + "\n \t\n".join(lines(d)[1:])
                + "\n\n").encode(), "accept"),
    ("',,' before the header", lambda d: (",,\n" + base(d)).encode(), "refuse"),
    ("'\"\"' before the header", lambda d: ('""\n' + base(d)).encode(), "refuse"),
    ("unterminated quote at the end", lambda d: (base(d)[:-1].rsplit(",", 1)[0] + ',"'
                                                  + base(d)[:-1].rsplit(",", 1)[1] + "\n")
     .encode(), "accept"),
    ("unterminated quote in the middle", lambda d: with_cell(d, 5, 2, '"0.5'), "refuse"),
    ("line ends inside quotes", lambda d: with_column(d, "note", ['"a\r\nb\rc"'] * N),
     "accept"),
    ("invalid UTF-8 in an ignored column", lambda d: with_column(d, "note", ["x"] * N)
     .replace(b"x", b"\xff", 1), "refuse"),
    ("overlong UTF-8", lambda d: with_column(d, "note", ["x"] * N).replace(b"x", b"\xc0\x80", 1),
     "refuse"),
    ("UTF-8 surrogate", lambda d: with_column(d, "note", ["x"] * N)
     .replace(b"x", b"\xed\xa0\x80", 1), "refuse"),
    ("UTF-8 cut at the end", lambda d: base(d).encode() + b"\xe2\x82", "refuse"),
    ("UTF-8 text in an ignored column", lambda d: with_column(d, "note", ["θ ≈ 0.5 €"] * N),
     "accept"),
    ("a second byte-order mark", lambda d: b"\xef\xbb\xbf\xef\xbb\xbf" + base(d).encode(),
     "refuse"),
    ("one data row", lambda d: "\n".join(lines(d)[:2]).encode(), "refuse"),
    ("a header only", lambda d: lines(d)[0].encode(), "refuse"),
    ("empty file", lambda d: b"", "refuse"),
    ("blank file", lambda d: b" \n\r\n\t\n", "refuse"),
    ("ragged row", lambda d: base(d).replace("\n", ",1\n", 7).replace(",1\n", "\n", 6)
     .encode(), "refuse"),
    ("t not increasing", lambda d: with_cell(d, 7, 0, rows(*d[2:])[5][0]), "refuse"),
    ("separated by spaces", lambda d: base(d, sep=" ").encode(), "refuse"),
    ("header by semicolons, data by commas",
     lambda d: ("t;u;y\n" + "\n".join(lines(d)[1:]) + "\n").encode(), "refuse"),
    ("a 100 000-character ignored field", lambda d: with_column(d, "note", ["x" * 100_000] * 3
                                                              + ["x"] * (N - 3)), "accept"),
    ("columns in another order", lambda d: text(["y", "t", "u"], [[r[2], r[0], r[1]] for r in
                                                                  rows(*d[2:])]).encode(),
     "accept"),
]


def outcome_cli(model: Path, data: Path, out: Path) -> tuple[int, np.ndarray | None]:
    # the harness is the paper's observer: the CLI runs the same method (its default is guarded)
    rc = main(["estimate", str(model), str(data), "--method", "paper", "-o", str(out),
               "--no-progress"])
    assert rc in (0, 2), f"thetahat estimate exited {rc}"
    return rc, (np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2) if rc == 0 else None)


def outcome_harness(exe: Path, data: Path) -> tuple[int, np.ndarray | None, str]:
    res = subprocess.run([str(exe), str(data)], capture_output=True, timeout=120)
    err = res.stderr.decode(errors="replace")
    assert res.returncode in (0, 2, 3), f"the harness exited {res.returncode}: {err}"
    table = (np.loadtxt(res.stdout.decode().splitlines()[1:], delimiter=",", ndmin=2)
             if res.returncode == 0 else None)
    return res.returncode, table, err


@pytest.mark.parametrize("make,expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_cli_and_harness_accept_and_refuse_alike(built, tmp_path, capsys, make, expected):
    model, exe, *_ = d = built["prop1"]
    data = tmp_path / "data.csv"
    data.write_bytes(make(d))
    rc_cli, est_cli = outcome_cli(model, data, tmp_path / "est.csv")
    cli_err = capsys.readouterr().err
    rc_c, est_c, c_err = outcome_harness(exe, data)
    assert (rc_cli == 0) == (expected == "accept"), f"thetahat estimate: {cli_err}"
    assert (rc_c == 0) == (expected == "accept"), f"harness: {c_err}"
    if expected == "accept":
        assert est_c.shape == est_cli.shape
        scale = np.maximum(np.abs(est_cli).max(axis=0), np.finfo(float).tiny)
        assert np.max(np.abs(est_c - est_cli) / scale) <= AGREE_RTOL
    else:
        assert "internal error" not in cli_err and "error:" in c_err


@pytest.mark.parametrize("header,expected", [
    ("t,u,y1,y2", "accept"), ("t,u1,y1,y2", "accept"), ("y2,t,u,y1", "accept"),
    ("t,u,u1,y1,y2", "refuse"), ("t,u,y,y2", "refuse"), ("t,u,y1,y2,y1", "refuse"),
    ("t,u,y1,y1", "refuse"), ("t,u,y1", "refuse"),
])
def test_two_outputs_by_name_and_by_number(built, tmp_path, capsys, header, expected):
    """two_inertia (outputs y1, y2): in any order, u or u1 for its one input; y (one output's
    name only), an input named twice, an output twice or missing: refused by both."""
    model, exe, t, u, y = built["two_inertia"]
    names = header.split(",")
    spec = load_model(model)
    wanted = {"t": t, "u": u[:, 0], "u1": u[:, 0]}
    for i, n in enumerate(spec.layout.output_names):
        wanted[n] = wanted[f"y{i + 1}"] = y[:, i]
    cols = [wanted.get(n, y[:, 0]) for n in names]
    data = tmp_path / "d.csv"
    data.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in r)
                                               for r in zip(*cols)) + "\n")
    rc_cli, est_cli = outcome_cli(model, data, tmp_path / "est.csv")
    rc_c, est_c, err = outcome_harness(exe, data)
    assert (rc_cli == 0) == (rc_c == 0) == (expected == "accept"), (capsys.readouterr().err,
                                                                     err)
    if expected == "accept":
        scale = np.maximum(np.abs(est_cli).max(axis=0), np.finfo(float).tiny)
        assert np.max(np.abs(est_c - est_cli) / scale) <= AGREE_RTOL


def test_documented_differences(built, tmp_path):
    """Where the harness must differ (docs/bad-input.md): a number longer than 1023
    characters, and steps other than dt, are refused with a message saying so."""
    model, exe, *_ = d = built["prop1"]
    long = tmp_path / "long.csv"
    long.write_bytes(with_cell(d, 5, 1, "0." + "0" * 1100 + "1"))
    rc, _, err = outcome_harness(exe, long)
    assert rc == 2 and "longer than FIELD_MAX = 1023" in err
    _, _, t, u, y = d
    jitter = tmp_path / "jitter.csv"
    jitter.write_text(text(["t", "u", "y"], rows(t * 1.01, u, y)))
    rc, _, err = outcome_harness(exe, jitter)
    assert rc == 2 and "not spaced by the generated dt" in err
