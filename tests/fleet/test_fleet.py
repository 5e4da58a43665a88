"""Fleet estimation in this process: one row per file, bad files reported, θ̂ per motor."""

import csv
import math

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.errors import ModelFileError
from thetahat.fleet import estimate_many, fleet_files

from fleet_data import CORRUPT, MODEL, N_FILES, true_theta, write_fleet

#: θ̂ at the end of a 10 s record at 20 Hz, noise 0.002 on y: within 0.06 of the motor's θ,
#: 1.5 % of Θ's width 4 (measured worst 0.028 over the 51 good records). The point: every
#: row is its own motor's θ, and the motors' θ are 0.27 apart.
THETA_ATOL = 0.06


def test_one_row_per_file_and_the_corrupt_one_reported(fleet, fleet_dir):
    assert [r["file"] for r in fleet.rows] == [str(p) for p in fleet_files(fleet_dir)]
    assert len(fleet.rows) == N_FILES and fleet.n_ok == N_FILES - 1
    (bad, reason), = fleet.failed.items()
    assert bad.endswith(CORRUPT)
    assert "ModelFileError" in reason and "not-a-number" in reason and "line 6" in reason
    assert math.isnan(fleet.rows[7]["theta_hat_theta"])


def test_theta_hat_is_each_motors_theta(fleet):
    for i, row in enumerate(fleet.rows):
        if row["status"] != "ok":
            continue
        truth = true_theta(i)
        assert abs(row["theta_hat_theta"] - truth) <= THETA_ATOL, row
        assert -2.0 <= row["theta_hat_theta"] <= 2.0                  # θ̂ ∈ Θ
        assert 0.0 <= row["t_settle_theta"] <= row["t_end"]
        assert 0.0 <= row["theta_hat_theta_se"] < 0.01
    settle = [r["t_settle_theta"] for r in fleet.rows if r["status"] == "ok"]
    assert np.median(settle) < 5.0            # θ̂ settles in the first half of most records


def test_chunking_does_not_change_results(fleet, fleet_dir):
    """Records sharing their sampling instants run as one batch: a different chunking sums
    in another order, so rows agree to rounding (run_batch's documented 5e-16 relative)."""
    other = estimate_many(MODEL, fleet_dir, chunk_size=5, progress=False)
    np.testing.assert_allclose(other.theta_hat(), fleet.theta_hat(), rtol=1e-12, atol=1e-14)


def test_fastest_back_end_agrees_with_the_numpy_batch(fleet, fleet_dir, monkeypatch):
    """With a C compiler the records run one by one on the C printed from the formulas; with
    THETAHAT_C=0 and a group below COMPILE_MIN_SAMPLES, as one NumPy batch (run_batch). They
    agree to the conformance matrix's 1e-9 relative (rounding only: sums in another order)."""
    from thetahat.codegen.loader import find_compiler
    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    import thetahat.fleet as fleet_mod
    chosen = []
    real = fleet_mod._group_runner

    def spy(obs, t, records):
        chosen.append(type(real(obs, t, records)).__name__)
        return real(obs, t, records)
    monkeypatch.setattr(fleet_mod, "_group_runner", spy)
    monkeypatch.setenv("THETAHAT_C", "0")
    # the observer's grouped runs: the paper's method (the default, guarded, fits per record)
    numpy_batch = estimate_many(MODEL, fleet_dir, chunk_size=8, progress=False, method="paper")
    assert set(chosen) == {"ModifiedHighGainObserver"}           # run_batch
    monkeypatch.delenv("THETAHAT_C")
    chosen.clear()
    fast = estimate_many(MODEL, fleet_dir, chunk_size=8, progress=False, method="paper")
    assert set(chosen) == {"NativeObserver"}
    assert [r["status"] for r in fast.rows] == [r["status"] for r in numpy_batch.rows]
    np.testing.assert_allclose(fast.theta_hat(), numpy_batch.theta_hat(), rtol=1e-9,
                               atol=1e-12)
    assert np.isfinite(fast.theta_hat()).sum() == N_FILES - 1     # all but the corrupt one


def test_parquet_records_and_outputs(tmp_path):
    pytest.importorskip("pyarrow")
    pd = pytest.importorskip("pandas")
    write_fleet(tmp_path, 6, corrupt=None, parquet_every=2)
    res = estimate_many(MODEL, tmp_path, progress=False)
    assert res.n_ok == 6
    assert sum(r["file"].endswith(".parquet") for r in res.rows) == 3
    res.write(tmp_path / "out" / "r.parquet")
    back = pd.read_parquet(tmp_path / "out" / "r.parquet")
    np.testing.assert_array_equal(back["theta_hat_theta"].to_numpy(), res.theta_hat()[:, 0])


def test_cli_fleet_mode(fleet_dir, tmp_path, capsys):
    out = tmp_path / "results.csv"
    assert main(["estimate", str(MODEL), str(fleet_dir / "m0*.csv"), "-o", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 10 and [r["status"] == "ok" for r in rows].count(False) == 1
    assert "1 failed" in capsys.readouterr().out


def test_no_files_is_a_clear_error(tmp_path):
    with pytest.raises(ModelFileError, match="no data files"):
        estimate_many(MODEL, tmp_path)


def test_cli_single_record_plot(fleet_dir, tmp_path):
    pytest.importorskip("matplotlib")
    fig = tmp_path / "fig.png"
    assert main(["estimate", str(MODEL), str(fleet_dir / "m00.csv"), "-o",
                 str(tmp_path / "e.csv"), "--plot", str(fig)]) == 0
    assert fig.stat().st_size > 10_000


def _with_dropouts(directory, source, name, rows=(40, 41, 90)):
    """A copy of a fleet record whose y is missing (empty cell) on a few rows."""
    lines = source.read_text().splitlines()
    for r in rows:
        t, u, _ = lines[r].split(",")
        lines[r] = f"{t},{u},"
    path = directory / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_nan_policy_reaches_every_record(fleet_dir, tmp_path):
    """A dropout fails its record under "raise" (the row says where) and is predicted over
    under "skip", where the record's θ̂ stays its motor's θ (3 missing of 201 samples)."""
    d = tmp_path / "drop"
    d.mkdir()
    _with_dropouts(d, fleet_dir / "m03.csv", "m03.csv")
    (d / "m04.csv").write_text((fleet_dir / "m04.csv").read_text())
    strict = estimate_many(MODEL, d, progress=False)
    assert strict.n_ok == 1 and "line 41" in strict.failed[str(d / "m03.csv")]
    skip = estimate_many(MODEL, d, nan_policy="skip", progress=False)
    assert skip.n_ok == 2
    assert abs(skip.rows[0]["theta_hat_theta"] - true_theta(3)) <= THETA_ATOL
    assert skip.rows[1]["theta_hat_theta"] == pytest.approx(strict.rows[1]["theta_hat_theta"],
                                                            rel=1e-12)


def test_parquet_dropouts_under_skip(tmp_path):
    pytest.importorskip("pyarrow")
    import pyarrow as pa
    import pyarrow.parquet as pq

    write_fleet(tmp_path, 2, corrupt=None, parquet_every=2)         # m01 is Parquet
    table = pq.read_table(tmp_path / "m01.parquet").to_pydict()
    table["y"][50] = float("nan")
    pq.write_table(pa.table(table), tmp_path / "m01.parquet")
    assert "row 50, column 'y': nan is not finite" in estimate_many(MODEL, tmp_path, progress=False).failed[
        str(tmp_path / "m01.parquet")]
    res = estimate_many(MODEL, tmp_path, nan_policy="skip", progress=False)
    assert res.n_ok == 2 and abs(res.rows[1]["theta_hat_theta"] - true_theta(1)) <= THETA_ATOL


def test_method_is_not_ignored(fleet_dir, tmp_path):
    """Fleet rows of the guarded method are that method's run on each record (an
    independent call of run_estimator), not the paper observer's."""
    from thetahat.io.datafile import read_data
    from thetahat.modelfile import load_model, run_estimator

    d = tmp_path / "two"
    d.mkdir()
    for name in ("m02.csv", "m09.csv"):
        (d / name).write_text((fleet_dir / name).read_text())
    res = estimate_many(MODEL, d, method="guarded", progress=False)
    paper = estimate_many(MODEL, d, method="paper", progress=False)
    spec = load_model(MODEL)
    for row, p_row, name in zip(res.rows, paper.rows, ("m02.csv", "m09.csv")):
        rec = read_data(d / name, spec.layout)
        ref = run_estimator(spec, rec.t, rec.u, rec.y, method="guarded")
        assert row["theta_hat_theta"] == pytest.approx(float(ref.theta_hat[-1, 0]), rel=1e-9)
        assert row["theta_hat_theta"] != p_row["theta_hat_theta"]


def test_unknown_method_or_policy_is_a_clear_error(fleet_dir):
    from thetahat.errors import OptionError

    with pytest.raises(OptionError, match="method must be one of"):
        estimate_many(MODEL, fleet_dir, method="kalman")
    with pytest.raises(OptionError, match="nan_policy must be one of"):
        estimate_many(MODEL, fleet_dir, nan_policy="drop")
