"""The estimates' writer: CSV that reads back to the same floats, by pyarrow's writer or by
NumPy, written atomically."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import DimensionError, FileAccessError
from thetahat.io import datafile
from thetahat.io.datafile import read_data, write_csv_table, write_estimates
from thetahat.io.mapping import RecordLayout
from thetahat.modelfile import load_model, run_estimator
from thetahat.modelfile.study import simulate_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

#: Values a formatter gets wrong first: a third, the smallest subnormal, the largest double,
#: signed zeros, numbers whose 17-digit form differs from their shortest one, infinities, NaN.
HOSTILE = np.array([1 / 3, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -0.0, 0.0,
                    0.1, 1e-7, 9.999999999999999e22, 123456789012345678.0, -2.5e-300,
                    np.inf, -np.inf, np.nan])


@pytest.fixture(params=["pyarrow", "numpy"])
def engine(request, monkeypatch) -> str:
    """pyarrow's CSV writer (whatever the size), or the NumPy path (pyarrow hidden)."""
    if request.param == "pyarrow":
        pytest.importorskip("pyarrow.csv")
        monkeypatch.setattr(datafile, "CSV_ARROW_MIN_VALUES", 0)
    else:
        monkeypatch.setitem(sys.modules, "pyarrow.csv", None)     # import pyarrow.csv fails
    return request.param


def _read(path) -> tuple[list[str], np.ndarray]:
    with open(path) as f:
        header = f.readline().rstrip("\n").split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def test_every_float_reads_back_bit_for_bit(tmp_path, engine):
    rng = np.random.default_rng(7)
    wide = rng.standard_normal(2000) * 10.0 ** rng.integers(-300, 300, 2000)
    columns = {"t": np.arange(HOSTILE.size + 0.0), "hostile": HOSTILE,
               "reversed": HOSTILE[::-1].copy()}
    path = tmp_path / "x.csv"
    write_csv_table(path, columns)
    header, table = _read(path)
    assert header == ["t", "hostile", "reversed"]
    for i, values in enumerate(columns.values()):
        assert table[:, i].tobytes() == values.tobytes()     # bits: -0.0 and NaN too
    write_csv_table(path, {"wide": wide})
    assert _read(path)[1][:, 0].tobytes() == wide.tobytes()


@pytest.mark.parametrize("model", ["lugre", "prop3", "two_inertia", "heater"])
def test_estimates_read_back_exactly(tmp_path, engine, model):
    """write_estimates of a real run, read back by NumPy: the same floats, every column."""
    spec = load_model(EXAMPLES / f"{model}.toml")
    data = simulate_model(spec, seed=3, t_end=spec.scenario.t_end / 10)
    res = run_estimator(spec, data.t, data.u, data.y, diagnose=False)
    path = tmp_path / "est.csv"
    write_estimates(path, res, spec.layout)
    header, table = _read(path)
    assert header[0] == "t" and len(header) == table.shape[1]
    expect = np.column_stack([res.t, res.x_hat, res.phi_hat, res.theta_hat]
                             + ([res.x_hat_refined] if res.x_hat_refined is not None else []))
    np.testing.assert_array_equal(table, expect)


def test_the_written_file_is_a_record_thetahat_reads(tmp_path, engine):
    t = np.arange(0.0, 1.0, 1e-3)
    path = tmp_path / "log.csv"
    write_csv_table(path, {"t": t, "u": np.sin(t), "y": 1e-3 * np.cos(t)})
    rec = read_data(path, RecordLayout(input_names=("u",), output_names=("y",)))
    assert rec.t.tobytes() == t.tobytes()
    assert rec.y[:, 0].tobytes() == (1e-3 * np.cos(t)).tobytes()


def test_a_failed_write_leaves_the_old_file(tmp_path, engine, monkeypatch):
    path = tmp_path / "x.csv"
    path.write_text("old\n")

    def fail(*args, **kwargs):
        raise OSError("disk full")

    if engine == "pyarrow":
        import pyarrow.csv
        monkeypatch.setattr(pyarrow.csv, "write_csv", fail)
    else:
        monkeypatch.setattr(datafile, "_write_csv_rows", fail)
    with pytest.raises(OSError, match="disk full"):
        write_csv_table(path, {"a": np.arange(3.0)})
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.csv"]    # no temporary left


def test_columns_of_different_lengths_are_refused(tmp_path):
    with pytest.raises(DimensionError, match="one length"):
        write_csv_table(tmp_path / "x.csv", {"a": np.zeros(3), "b": np.zeros(4)})
    with pytest.raises(DimensionError, match="one-dimensional"):
        write_csv_table(tmp_path / "x.csv", {"a": np.zeros((3, 2))})
    assert not (tmp_path / "x.csv").exists()


def test_an_input_is_never_overwritten(tmp_path):
    t = np.arange(0.0, 0.1, 1e-3)
    path = tmp_path / "log.csv"
    write_csv_table(path, {"t": t, "u": t, "y": t})
    before = path.read_bytes()
    read_data(path, RecordLayout(input_names=("u",), output_names=("y",)))
    with pytest.raises(FileAccessError):
        write_csv_table(path, {"t": t})
    assert path.read_bytes() == before
