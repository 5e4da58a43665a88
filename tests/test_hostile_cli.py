"""Issue 37 (hostile round 3), the command line: every error a user can reach names a fix
they can apply where they are.

A record of 2–11 samples is too short to estimate the output noise level σ from (it needs
12); ``thetahat estimate`` used to answer "pass noise_std", an option it did not have. It now
has ``--noise-std`` (one σ, or one per output), for one record and for a fleet, and the
message names it, and the longer record, for every method.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.modelfile import load_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
METHODS = ("paper", "guarded", "mle", "ekf")


def run(args: list[str]) -> int:
    """``main``'s exit code, also when argparse exits."""
    try:
        return main(args)
    except SystemExit as exc:
        return int(exc.code or 0)


def short_record(path: Path, n: int, model: str = "prop1") -> Path:
    spec = load_model(EXAMPLES / f"{model}.toml")
    t = np.arange(n) * 0.01
    cols = [t] + [np.sin(t + i) for i in range(spec.system.m)] \
        + [0.1 * np.cos(t + i) for i in range(spec.system.r)]
    head = ["t"] + list(spec.layout.input_names) + list(spec.layout.output_names)
    path.write_text(",".join(head) + "\n" + "\n".join(",".join(repr(float(v)) for v in row)
                                                       for row in zip(*cols)) + "\n")
    return path


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("n", (2, 6, 11))
def test_a_short_record_names_the_option_that_estimates_it(tmp_path, capsys, method, n):
    data = short_record(tmp_path / "d.csv", n)
    out = tmp_path / "est.csv"
    model = str(EXAMPLES / "prop1.toml")
    args = ["estimate", model, str(data), "-o", str(out), "--no-progress", "--method", method]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--noise-std" in err and "at least 12 samples" in err, err
    assert "internal error" not in err and not out.exists()
    assert main([*args, "--noise-std", "0.01"]) == 0, capsys.readouterr().err
    est = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    assert est.shape[0] == n and np.isfinite(est).all()
    theta = est[:, out.read_text().splitlines()[0].split(",").index("theta_hat_theta")]
    assert np.all((theta >= -0.5 - 1e-12) & (theta <= 0.5 + 1e-12))   # θ̂ in Θ = [-0.5, 0.5]


@pytest.mark.parametrize("model", ("prop1", "two_inertia", "heater"))
def test_noise_std_per_output_and_its_errors(tmp_path, capsys, model):
    """One σ or one per output; another count, a σ ≤ 0, NaN or text: exit 2 naming the
    option (three shipped models besides LuGre, one with two outputs)."""
    spec = load_model(EXAMPLES / f"{model}.toml")
    r = spec.system.r
    data = short_record(tmp_path / "d.csv", 8, model)
    args = ["estimate", str(EXAMPLES / f"{model}.toml"), str(data), "-o",
            str(tmp_path / "e.csv"), "--no-progress", "--method", "ekf", "--noise-std"]
    assert main([*args, "0.01"]) == 0, capsys.readouterr().err
    assert main([*args, ",".join(["0.01"] * r)]) == 0, capsys.readouterr().err
    for bad in (",".join(["0.01"] * (r + 1)), "0", "-1", "nan", "inf", "abc", ""):
        assert run([*args, bad]) == 2, bad
        err = capsys.readouterr().err
        assert "--noise-std" in err and "internal error" not in err, (bad, err)


@pytest.mark.parametrize("method", ("ekf", "paper"))
def test_a_fleet_of_short_records_takes_noise_std(tmp_path, capsys, method):
    folder = tmp_path / "logs"
    folder.mkdir()
    for i, n in enumerate((3, 7, 30)):
        short_record(folder / f"r{i}.csv", n)
    out = tmp_path / "results.csv"
    args = ["estimate", str(EXAMPLES / "prop1.toml"), str(folder), "-o", str(out),
            "--no-progress", "--method", method]
    assert main(args) == 0
    err = capsys.readouterr().err
    if method == "ekf":                 # the two short ones fail, saying what to do
        assert err.count("--noise-std") == 2, err
    assert "RuntimeWarning" not in err           # no stray NumPy warning on a short record
    assert main([*args, "--noise-std", "0.01"]) == 0
    assert "failed" not in capsys.readouterr().err
    import csv
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 3 and all(row["status"] == "ok" for row in rows), rows
