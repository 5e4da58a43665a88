"""Issue 37, hostile input round 3: the readers, fleets and outputs.

Each case is reproduced as reported and asserts the typed error and a message that names the
file's problem and the fix, or the correct result: no internal error, no crash, no hang, no
silent acceptance, no lost results.
"""

from __future__ import annotations

import io
import os
import re
import signal
import struct
import subprocess
import sys
import time
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import scipy.sparse

from thetahat import errors as E
from thetahat import limits
from thetahat.cli import main
from thetahat.fleet import check_output, estimate_many, fleet_files
from thetahat.io.datafile import read_data
from thetahat.modelfile import EXAMPLE_MODEL, loads_model

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
#: Hostile input must fail fast; generous against a loaded 2-core machine.
FAST_SECONDS = 10.0
LAYOUT = loads_model(EXAMPLE_MODEL).layout
MAPPED = EXAMPLE_MODEL + '[data]\nt = "time"\nu = "volts"\ny = { column = "pos", scale = 1e-3 }\n'
N = 50


def _t() -> np.ndarray:
    return np.arange(N) * 0.01


def _mat(path: Path, variables: dict, **kw) -> Path:
    scipy.io.savemat(path, variables, **kw)
    return path


def _good_mat(path: Path, **kw) -> Path:
    t = _t()
    return _mat(path, {"t": t, "u": np.sin(t), "y": np.cos(t)}, **kw)


# --- MATLAB files: damaged, truncated, hostile --------------------------------------------------

def _v5_header() -> bytes:
    text = b"MATLAB 5.0 MAT-file, written by a test".ljust(116, b" ")
    return text + bytes(8) + struct.pack("<H", 0x0100) + b"IM"


def _matrix(name: bytes, dims: tuple[int, ...], cls: int = 6, flags: int = 0,
            data: bytes = b"") -> bytes:
    """A v5 miMATRIX element's content (array flags, dims, name, real part)."""
    body = struct.pack("<IIII", 6, 8, cls | (flags << 8), 0)
    body += struct.pack("<II", 5, 4 * len(dims)) + struct.pack(f"<{len(dims)}i", *dims)
    body += bytes(-len(body) % 8)
    body += struct.pack("<II", 1, len(name)) + name + bytes(-len(name) % 8)
    body += struct.pack("<II", 9, len(data)) + data + bytes(-len(data) % 8)
    return body


def _bomb(path: Path, declared: int) -> Path:
    """t and u, then a compressed y whose matrix declares ``declared`` bytes, 3 MB on disk."""
    t = _t()
    head = _mat(path, {"t": t, "u": np.sin(t)}, do_compression=True).read_bytes()
    inner = struct.pack("<II", 14, declared) + _matrix(b"y", (declared // 8, 1))[:48]
    stream = zlib.compress(inner + bytes(3_000_000 * 200), 9)
    path.write_bytes(head + struct.pack("<II", 15, len(stream)) + stream)
    return path


def _flip_in_compressed(path: Path) -> Path:
    data = bytearray(_good_mat(path, do_compression=True).read_bytes())
    end = 128 + 8 + struct.unpack_from("<I", data, 132)[0]     # the first variable, 't'
    data[(128 + end) // 2 + 20] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def _v4_sparse(path: Path) -> Path:
    t = _t()
    return _mat(path, {"t": t[:, None], "u": np.sin(t)[:, None],
                       "y": scipy.sparse.csc_matrix(np.cos(t)[:, None])}, format="4")


def _class_99(path: Path) -> Path:
    data = _good_mat(path).read_bytes()
    at = data.index(struct.pack("<II", 6, 8), 128 + 8) + 8      # array flags of 't'
    patched = bytearray(data)
    patched[at] = 99
    path.write_bytes(bytes(patched))
    return path


def _huge_element(path: Path) -> Path:
    path.write_bytes(_v5_header() + struct.pack("<II", 14, 4_000_000_000)
                     + _matrix(b"t", (500_000_000, 1)) + bytes(5000))
    return path


MAT_CASES = [
    ("empty", lambda p: (p.write_bytes(b""), p)[1], E.ModelFileError, "it is empty"),
    ("100-byte header", lambda p: (p.write_bytes(_v5_header()[:100]), p)[1],
     E.ModelFileError, "fewer than the 128-byte header"),
    ("v4 sparse y", _v4_sparse, E.ModelFileError, "'y': a sparse matrix; save the signal as a "
                                                  "full vector: full(x)"),
    ("class 99", _class_99, E.ModelFileError, "'t': of unknown class 99: the file is damaged"),
    ("flipped byte in a compressed element", _flip_in_compressed, E.ModelFileError,
     "the compressed element at byte 128 is damaged (Error -3"),
    ("zlib bomb declaring 3.4 GB", lambda p: _bomb(p, 3_400_000_000),
     E.InputLimitError, "declares 3400000000 bytes once decompressed"),
    ("5 KB element declaring 4 GB", _huge_element, E.ModelFileError,
     "declares 4000000000 bytes, but only 5"),
    ("bomb declaring less than it holds", lambda p: _bomb(p, 4096),
     E.ModelFileError, "'y': its compressed element expands beyond the 4096 bytes"),
    ("logical y", lambda p: _mat(p, {"t": _t(), "u": _t(), "y": _t() > 0.2}), E.ModelFileError,
     "'y': a logical (true/false) array, not numbers; save it as double"),
    ("v5 sparse u", lambda p: _mat(p, {"t": _t(), "u": scipy.sparse.csc_matrix(_t()[:, None]),
                                       "y": _t()}), E.ModelFileError, "'u': a sparse matrix"),
    ("complex y", lambda p: _mat(p, {"t": _t(), "u": _t(), "y": _t() * 1j}), E.ModelFileError,
     "'y': complex values"),
    ("text u", lambda p: _mat(p, {"t": _t(), "u": "volts", "y": _t()}), E.ModelFileError,
     "'u': not numeric (a char)"),
    ("v7.3", lambda p: (p.write_bytes(b"MATLAB 7.3 MAT-file".ljust(512, b" ")
                                      + b"\x89HDF\r\n\x1a\n"), p)[1], E.ModelFileError,
     "save('d.mat', '-v7')"),
]


@pytest.mark.parametrize("name,make,error,words", MAT_CASES, ids=[c[0] for c in MAT_CASES])
def test_mat_files_fail_typed_and_named(tmp_path, name, make, error, words):
    path = make(tmp_path / "d.mat")
    start = time.perf_counter()
    with pytest.raises(error) as info:
        read_data(path, LAYOUT)
    assert time.perf_counter() - start < FAST_SECONDS
    assert words in str(info.value) and str(path) in str(info.value)


def test_mat_files_that_are_fine_still_read(tmp_path):
    """Compressed (the default of MATLAB's v7) and v4 files give the values written."""
    for name, kw in (("c.mat", {"do_compression": True}), ("v4.mat", {"format": "4"})):
        rec = read_data(_good_mat(tmp_path / name, **kw), LAYOUT)
        np.testing.assert_array_equal(rec.y[:, 0], np.cos(_t()))


def test_mat_file_unused_bomb_is_not_expanded(tmp_path, monkeypatch):
    """Only the variables a record uses are decompressed: an unused compressed variable that
    is larger than allowed is never expanded (its declared size is within the limit)."""
    path = _good_mat(tmp_path / "d.mat", do_compression=True)
    with path.open("ab") as fh:
        stream = zlib.compress(struct.pack("<II", 14, 80_000_000)
                               + _matrix(b"big", (10_000_000, 1))[:48] + bytes(80_000_000))
        fh.write(struct.pack("<II", 15, len(stream)) + stream)
    rec = read_data(path, LAYOUT)
    assert rec.t.size == N
    monkeypatch.setattr(limits, "MAX_DECOMPRESSED_BYTES", 1_000_000)
    with pytest.raises(E.InputLimitError, match="MAX_DECOMPRESSED_BYTES"):
        read_data(path, LAYOUT)                 # declared sizes are checked for every element


# --- Parquet: bounded by the metadata, every kind named -------------------------------------------

def _parquet(path: Path, columns: dict) -> Path:
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    pq.write_table(pa.table(columns), path)
    return path


def test_parquet_row_count_is_checked_before_reading(tmp_path, monkeypatch):
    """The issue's 2 MB file of 134 M rows: the row count comes from the metadata and is
    refused before a column is read (the limit lowered so the test writes 2000 rows)."""
    path = _parquet(tmp_path / "d.parquet", {"t": np.arange(2000.0), "u": np.zeros(2000),
                                             "y": np.zeros(2000)})
    monkeypatch.setattr(limits, "MAX_DATA_SAMPLES", 1000)
    with pytest.raises(E.InputLimitError, match=r"declares 2000 rows, more than the limit of "
                                                r"1000 samples.*MAX_DATA_SAMPLES"):
        read_data(path, LAYOUT)


def _decimal(t):
    import decimal
    pa = pytest.importorskip("pyarrow")
    return pa.array([decimal.Decimal(f"{v:.2f}") for v in t], pa.decimal128(10, 2))


def _nulls(t):
    pa = pytest.importorskip("pyarrow")
    return pa.nulls(t.size)


PARQUET_KINDS = [
    ("timestamp y", lambda t: np.datetime64("2024-01-01", "ns")
     + np.arange(t.size).astype("timedelta64[s]"), "holds time stamps"),
    ("all-null y", _nulls, "holds no values (every entry is null)"),
    ("bool y", lambda t: t > 0.1, "holds booleans (true/false)"),
    ("text y", lambda t: [f"{v}" for v in t], "holds text"),
]


@pytest.mark.parametrize("mapped", [False, True], ids=["plain", "mapped"])
@pytest.mark.parametrize("name,column,words", PARQUET_KINDS, ids=[c[0] for c in PARQUET_KINDS])
def test_parquet_kinds_are_named_with_or_without_a_mapping(tmp_path, name, column, words,
                                                           mapped):
    t = _t()
    y_name = "pos" if mapped else "y"
    path = _parquet(tmp_path / "d.parquet", {"time" if mapped else "t": t,
                                             "volts" if mapped else "u": t, y_name: column(t)})
    layout = loads_model(MAPPED).layout if mapped else LAYOUT
    with pytest.raises(E.ModelFileError, match=re.escape(f"column '{y_name}': {words}")):
        read_data(path, layout)


def test_parquet_decimal_is_read_as_numbers(tmp_path):
    t = _t()
    rec = read_data(_parquet(tmp_path / "d.parquet", {"t": t, "u": t, "y": _decimal(t)}),
                    LAYOUT)
    np.testing.assert_allclose(rec.y[:, 0], np.round(t, 2), rtol=0, atol=1e-15)


# --- the [data]-mapped path is the plain path plus a step ----------------------------------------

def _csv(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


MAPPED_CSV_CASES = [
    ("1_000 cell", "time,volts,pos\n0,1_000,1\n0.01,0,2\n", "column 'volts': '1_000' is not a "
     "number (digit separators", "column 'u': '1_000' is not a number (digit separators"),
    ("duplicated y column", "time,volts,pos,pos\n0,0,1,1\n0.01,0,2,2\n",
     "the column(s) ['pos'] appear more than once", "the column(s) ['y'] appear more than once"),
    ("mapped column missing", "time,volts,position\n0,0,1\n0.01,0,2\n",
     "no column 'pos' (mapped to y by the model file's [data] table)", "missing column 'y'"),
]


@pytest.mark.parametrize("name,text,words,plain_words", MAPPED_CSV_CASES,
                         ids=[c[0] for c in MAPPED_CSV_CASES])
def test_mapped_csv_has_the_plain_rules(tmp_path, name, text, words, plain_words):
    """With a [data] table as without: the same file, renamed, fails the same way."""
    with pytest.raises(E.ModelFileError, match=re.escape(words)):
        read_data(_csv(tmp_path / "d.csv", text), loads_model(MAPPED).layout)
    plain = text.replace("time", "t").replace("volts", "u").replace("pos", "y")
    with pytest.raises(E.ModelFileError, match=re.escape(plain_words)):
        read_data(_csv(tmp_path / "p.csv", plain), LAYOUT)


def test_cr_only_line_ends_are_read_and_a_nul_is_refused(tmp_path):
    """The rules the C harness must match (docs/bad-input.md): CR alone ends a line; a NUL
    byte in a cell is not a number."""
    rec = read_data(_csv(tmp_path / "cr.csv", "t,u,y\r0,1,2\r0.01,1,3\r"), LAYOUT)
    assert rec.y[:, 0].tolist() == [2.0, 3.0]
    with pytest.raises(E.ModelFileError, match=r"line 3, column 'y': '3\\x00' is not a number"):
        read_data(_csv(tmp_path / "nul.csv", "t,u,y\n0,1,2\n0.01,1,3\x00\n"), LAYOUT)


def test_one_column_mapped_to_both_u_and_y_is_refused(tmp_path):
    spec = loads_model(EXAMPLE_MODEL + '[data]\nu = "a"\ny = "a"\n')
    path = _csv(tmp_path / "d.csv", "t,a\n0,1\n0.01,2\n")
    with pytest.raises(E.ModelFileError, match="column 'a' is used for both u and y"):
        read_data(path, spec.layout)
    spec = loads_model(EXAMPLE_MODEL + '[data]\nu = "y"\n')     # mapped u = the default y
    with pytest.raises(E.ModelFileError, match="column 'y' is used for both u and y"):
        read_data(_csv(tmp_path / "e.csv", "t,y\n0,1\n0.01,2\n"), spec.layout)


@pytest.mark.parametrize("scale,words", [
    ("1e307", r"1e\+307 × 100.0 \+ 0 overflows float64"),
    ("1e-320", r"1e-320 × 1.0 \+ 0 underflows to zero or a subnormal number"),
], ids=["overflow", "underflow"])
def test_scale_is_applied_before_the_checks(tmp_path, scale, words):
    spec = loads_model(EXAMPLE_MODEL + f'[data]\ny = {{ column = "y", scale = {scale} }}\n')
    path = _csv(tmp_path / "d.csv", "t,u,y\n0,0,1\n0.01,0,100\n0.02,0,2\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(E.ModelFileError, match=f"line \\d, column 'y': {words}; check the "
                                                   r"\[data\] table's scale"):
            read_data(path, spec.layout)
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]


@pytest.mark.parametrize("model", ["prop1", "two_inertia", "spring_friction", "lugre"])
def test_time_in_milliseconds_is_flagged(tmp_path, model):
    """t written in ms (whole numbers stepping by 1) on models whose slowest time constant is
    at most 1.3 s: warned, with the [data] line that converts it; the same record in seconds
    is not."""
    spec = loads_model((EXAMPLES / f"{model}.toml").read_text(), source=model)
    names = ",".join(["t", *spec.input_names, *spec.output_names])
    k = np.arange(200)
    cols = [k] + [np.sin(k * 1e-3)] * (spec.layout.m + spec.layout.r)
    ms = tmp_path / "ms.csv"
    np.savetxt(ms, np.column_stack(cols), delimiter=",", header=names, comments="", fmt="%.17g")
    with pytest.warns(E.ThetahatWarning, match=r"Is t in milliseconds.*scale = 1e-3"):
        read_data(ms, spec.layout)
    cols[0] = k * 1e-3
    np.savetxt(ms, np.column_stack(cols), delimiter=",", header=names, comments="", fmt="%.17g")
    with warnings.catch_warnings():
        warnings.simplefilter("error", E.ThetahatWarning)
        assert read_data(ms, spec.layout).t[-1] == pytest.approx(0.199)


def test_whole_seconds_of_a_slow_plant_are_not_flagged(tmp_path):
    """The heater (slowest time constant 2205 s) logged every second: legitimate."""
    spec = loads_model((EXAMPLES / "heater.toml").read_text(), source="heater")
    k = np.arange(300.0)
    path = tmp_path / "h.csv"
    np.savetxt(path, np.column_stack([k, np.ones_like(k), 300 + k / 100]), delimiter=",",
               header=",".join(["t", *spec.input_names, *spec.output_names]), comments="")
    with warnings.catch_warnings():
        warnings.simplefilter("error", E.ThetahatWarning)
        assert read_data(path, spec.layout).t.size == 300


# --- fleets ---------------------------------------------------------------------------------------

def _record(path: Path, n: int = 120) -> Path:
    t = np.arange(n) * 0.01
    np.savetxt(path, np.c_[t, np.sin(t), 0.1 * np.cos(t)], delimiter=",", header="t,u,y",
               comments="", fmt="%.17g")
    return path


@pytest.fixture
def model(tmp_path) -> Path:
    path = tmp_path / "m.toml"
    path.write_text(EXAMPLE_MODEL, encoding="utf-8")
    return path


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_fleet_with_a_non_utf8_file_name_writes_every_row(tmp_path, model, suffix):
    if suffix == ".parquet":
        pytest.importorskip("pyarrow")
    d = tmp_path / "logs"
    d.mkdir()
    _record(d / "a.csv")
    odd = Path(os.fsdecode(bytes(d) + b"/b\xff.csv"))
    _record(odd)
    res = estimate_many(model, d, progress=False)
    assert res.n_ok == 2
    out = res.write(tmp_path / f"r{suffix}")
    if suffix == ".csv":
        text = out.read_text(encoding="utf-8")          # valid UTF-8
        assert "b\\xff.csv" in text and text.count("\nok") + text.count(",ok,") >= 2
    else:
        import pyarrow.parquet as pq
        files = pq.read_table(out).column("file").to_pylist()
        assert files[1].endswith("b\\xff.csv")


def test_glob_star_star_follows_no_symlink_loop(tmp_path):
    d = tmp_path / "logs"
    (d / "sub").mkdir(parents=True)
    _record(d / "a.csv")
    _record(d / "sub" / "b.csv")
    (d / "self").symlink_to(d)                              # one loop: a.csv 41 times before
    (d / "sub" / "up").symlink_to(d)                        # two loops: no answer before
    start = time.perf_counter()
    files = fleet_files(f"{d}/**/*.csv")
    assert time.perf_counter() - start < FAST_SECONDS
    assert sorted(p.name for p in files) == ["a.csv", "b.csv"]


def test_folder_and_glob_take_the_same_records(tmp_path):
    d = tmp_path / "logs"
    d.mkdir()
    _record(d / "a.csv")
    _good_mat(d / "b.mat")
    (d / "notes.txt").write_text("not a record")
    (d / ".a.csv.1f2e.tmp.csv").write_text("a temporary file")
    assert [p.name for p in fleet_files(d)] == ["a.csv", "b.mat"]
    assert fleet_files(d) == fleet_files(f"{d}/*") == fleet_files(f"{d}/**/*")


@pytest.mark.parametrize("layout", ["marker", "hive", "parts"])
def test_partitioned_parquet_dataset_is_not_a_fleet(tmp_path, model, layout):
    d = tmp_path / "dataset"
    d.mkdir()
    if layout == "hive":
        (d / "motor=1").mkdir()
        _record(d / "motor=1" / "x.csv")
    else:
        _record(d / "part-0.parquet")
        _record(d / "part-1.parquet")
        if layout == "marker":
            (d / "_common_metadata").write_bytes(b"")
    with pytest.raises(E.ModelFileError, match="looks like one partitioned Parquet dataset.*"
                                               "Combine the parts into one file"):
        fleet_files(d)


def test_glob_fleet_may_not_write_where_its_glob_reads(tmp_path, model, capsys):
    d = tmp_path / "logs"
    d.mkdir()
    _record(d / "m1.csv")
    with pytest.raises(E.ModelFileError, match="the fleet's glob .* matches it"):
        check_output(d / "results.csv", model, fleet_files(f"{d}/*.csv"), f"{d}/*.csv")
    assert main(["estimate", str(model), f"{d}/**/*.csv", "-o", str(d / "r.csv")]) == 2
    assert "matches it" in capsys.readouterr().err and not (d / "r.csv").exists()
    out = check_output(tmp_path / "results.csv", model, fleet_files(f"{d}/*.csv"),
                       f"{d}/*.csv")
    assert out.parent == tmp_path


# --- outputs --------------------------------------------------------------------------------------

_WRITER = """
import os, signal, sys, time
from pathlib import Path
from thetahat.safe_io import atomic_path
out = Path(sys.argv[1])
with atomic_path(out) as tmp:
    tmp.write_bytes(b"x" * 2_000_000)
    print("writing", flush=True)
    time.sleep(60)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_signal_during_a_write_leaves_no_temporary(tmp_path, sig):
    out = tmp_path / "est.csv"
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(out)], stdout=subprocess.PIPE,
                            env=env)
    try:
        assert proc.stdout.readline().strip() == b"writing"
        assert len(os.listdir(tmp_path)) == 1               # the hidden temporary folder
        proc.send_signal(sig)
        assert proc.wait(timeout=FAST_SECONDS) == -sig      # the signal's own ending
    finally:
        proc.kill()
        proc.wait()
    assert os.listdir(tmp_path) == []


def test_temporary_is_never_a_record(tmp_path):
    """While a result is written, a folder fleet over its folder sees no temporary file."""
    from thetahat.safe_io import atomic_path

    _record(tmp_path / "a.csv")
    with atomic_path(tmp_path / "results.csv") as tmp:
        _record(tmp)
        assert [p.name for p in fleet_files(tmp_path)] == ["a.csv"]
        assert [p.name for p in fleet_files(f"{tmp_path}/**/*.csv")] == ["a.csv"]


def test_long_output_name_works_and_too_long_is_refused_first(tmp_path, model, capsys):
    data = _record(tmp_path / "d.csv")
    long_name = tmp_path / ("e" * 236 + ".csv")                  # 240 characters
    assert main(["estimate", str(model), str(data), "-o", str(long_name), "--no-progress"]) == 0
    assert long_name.stat().st_size > 0
    capsys.readouterr()
    too_long = tmp_path / ("e" * 300 + ".csv")
    assert main(["estimate", str(model), str(tmp_path / "missing.csv"), "-o",
                 str(too_long)]) == 2                             # refused before reading
    err = capsys.readouterr().err
    assert "more than the 255 the file system allows" in err and "missing.csv" not in err
