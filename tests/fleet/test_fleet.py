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
