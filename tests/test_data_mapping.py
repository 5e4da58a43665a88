"""The [data] table and MATLAB files (issue 19): mapped t, u, y from MAT, CSV and Parquet."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from thetahat.io.datafile import read_data
from thetahat.errors import ModelFileError, ThetahatError
from thetahat.modelfile import EXAMPLE_MODEL, loads_model

ROOT = Path(__file__).resolve().parents[1]
#: Scaling is one multiply-add in float64: exact to a few ulps of the values (~1e2).
EXACT = 1e-12

MAPPED = EXAMPLE_MODEL + """
[data]
t = "time"
u = { column = "volts", scale = 35.15, offset = -1.5 }
y = { column = "pos_mm", scale = 1e-3 }
"""


def _record(n: int = 50) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(19)
    return {"time": np.arange(n) * 1e-3, "volts": rng.normal(size=n),
            "pos_mm": rng.normal(size=n) * 100}


def _check(record, raw) -> None:
    np.testing.assert_allclose(record.t, raw["time"], rtol=0, atol=EXACT)
    np.testing.assert_allclose(record.u[:, 0], 35.15 * raw["volts"] - 1.5, rtol=EXACT)
    np.testing.assert_allclose(record.y[:, 0], 1e-3 * raw["pos_mm"], rtol=EXACT)


@pytest.mark.parametrize("orient", ["row", "column"])
def test_mat_round_trip_with_scale_and_offset(tmp_path, orient):
    raw = _record()
    shaped = {k: (v[None, :] if orient == "row" else v[:, None]) for k, v in raw.items()}
    shaped["notes"] = np.array(["unused text is not an error"])
    path = tmp_path / "log.mat"
    scipy.io.savemat(path, shaped)
    record = read_data(path, loads_model(MAPPED).layout)
    assert record.u.shape == (50, 1) and record.y.shape == (50, 1)
    assert record.columns == ("time", "volts", "pos_mm")
    _check(record, raw)


def test_mat_without_mapping_uses_default_names(tmp_path):
    path = tmp_path / "plain.mat"
    scipy.io.savemat(path, {"t": [0.0, 0.1, 0.2], "u": [1.0, 2.0, 3.0], "y": [4.0, 5.0, 6.0]})
    record = read_data(path, loads_model(EXAMPLE_MODEL).layout)
    assert record.y[:, 0].tolist() == [4.0, 5.0, 6.0]


def test_rate_instead_of_time_vector(tmp_path):
    raw = _record()
    path = tmp_path / "norate.mat"
    scipy.io.savemat(path, {"volts": raw["volts"], "pos_mm": raw["pos_mm"]})
    spec = loads_model(MAPPED.replace('t = "time"', "t = { rate = 1000, start = 2.0 }"))
    record = read_data(path, spec.layout)
    np.testing.assert_allclose(record.t, 2.0 + np.arange(50) / 1000.0, rtol=EXACT)
    assert record.columns[0] == "rate=1000 Hz"


def test_mat_v73_is_refused_with_how_to_resave(tmp_path):
    path = tmp_path / "big.mat"
    try:
        import h5py
    except ImportError:                     # the v7.3 layout: 512-byte header, then HDF5
        header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 2024 HDF5"
        path.write_bytes(header.ljust(512, b" ") + b"\x89HDF\r\n\x1a\n" + bytes(64))
    else:
        with h5py.File(path, "w") as fh:
            fh["qm"] = np.zeros(5)
    with pytest.raises(ModelFileError, match=r"v7\.3.*-v7.*CSV"):
        read_data(path, loads_model(MAPPED).layout)


@pytest.mark.parametrize("bad, match", [
    ({"volts": "text"}, r"variable 'volts'.*not numeric.*the file has .*'pos_mm'"),
    ({"volts": np.arange(50) * (1 + 1j)}, r"variable 'volts'.*complex"),
    ({"volts": np.ones((50, 2))}, r"variable 'volts'.*50×2 array, not a vector"),
    ({"volts": np.ones(49)}, r"variable 'volts'.*49 samples, but 'time' has 50"),
    ({"volts": np.array([np.ones(3), np.ones(4)], dtype=object)}, r"'volts'.*not numeric"),
])
def test_bad_mat_variable_is_named(tmp_path, bad, match):
    path = tmp_path / "bad.mat"
    scipy.io.savemat(path, {**_record(), **bad})
    with pytest.raises(ModelFileError, match=match):
        read_data(path, loads_model(MAPPED).layout)


def test_unknown_variable_lists_the_available_ones(tmp_path):
    path = tmp_path / "log.mat"
    scipy.io.savemat(path, _record())
    spec = loads_model(MAPPED.replace('"pos_mm"', '"position"'))
    with pytest.raises(ModelFileError, match=r"no variable 'position' \(mapped to y by the "
                                             r"model file's \[data\] table\); the file has "
                                             r"'time' \(1×50 double\), 'volts'"):
        read_data(path, spec.layout)


def test_non_finite_input_and_non_increasing_t_are_named(tmp_path):
    raw = _record()
    raw["volts"][7] = np.inf
    path = tmp_path / "inf.mat"
    scipy.io.savemat(path, raw)
    with pytest.raises(ModelFileError, match=r"sample 7, variable 'volts': inf is not finite"):
        read_data(path, loads_model(MAPPED).layout)
    raw = _record()
    raw["time"][10] = raw["time"][9]
    scipy.io.savemat(path, raw)
    with pytest.raises(ModelFileError, match=r"sample 10: t = .* does not increase \(previous .*'time'"):
        read_data(path, loads_model(MAPPED).layout)


def test_csv_mapping(tmp_path):
    raw = _record()
    path = tmp_path / "log.csv"
    cols = ["extra", "pos_mm", "time", "volts"]
    table = np.column_stack([np.zeros(50)] + [raw[c] for c in cols[1:]])
    np.savetxt(path, table, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")
    _check(read_data(path, loads_model(MAPPED).layout), raw)
    bad = path.read_text().replace("\n0,", "\n0,oops,", 1).replace(",oops,", ",oops", 1)
    path.write_text(bad)
    with pytest.raises(ModelFileError, match=r"column 'pos_mm': 'oops.*' is not a number"):
        read_data(path, loads_model(MAPPED).layout)


def test_parquet_mapping(tmp_path):
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    raw = _record()
    path = tmp_path / "log.parquet"
    pq.write_table(pa.table({**raw, "label": ["x"] * 50}), path)
    _check(read_data(path, loads_model(MAPPED).layout), raw)
    spec = loads_model(MAPPED.replace('"pos_mm"', '"label"'))
    with pytest.raises(ModelFileError, match=r"column 'label': holds text, not numbers"):
        read_data(path, spec.layout)


@pytest.mark.parametrize("table, match", [
    ('u = { column = "v", gain = 2 }', r"\[data\]: u: unknown key\(s\) \['gain'\]"),
    ('u = { column = "v", scale = "2" }', r"\[data\]: u scale: expected a finite number"),
    ('u = { column = "v", scale = 0 }', r"u scale: 0 would erase"),
    ('u = ["a", "b"]', r"u: expected 1 signal\(s\), one per name in \[perturbation\] u"),
    ("y = 3", r"\[data\]: y: expected a variable name"),
    ("t = { rate = -1 }", r"t rate \(Hz\): expected a finite positive number"),
    ('x = "q"', r"\[data\]: unknown key\(s\) \['x'\]"),
])
def test_bad_data_table_is_refused_by_the_model_file(table, match):
    with pytest.raises(ModelFileError, match=match):
        loads_model(EXAMPLE_MODEL + "[data]\n" + table + "\n")


def test_json_model_file_has_the_same_data_table():
    import tomllib

    doc = tomllib.loads(MAPPED)
    spec = loads_model(json.dumps(doc), syntax="json")
    assert spec.data == loads_model(MAPPED).data
    assert spec.data.u[0].scale == 35.15 and spec.data.t.column == "time"


def test_errors_are_thetahat_errors():
    assert issubclass(ModelFileError, ThetahatError)


def test_emps_model_file_reads_the_shipped_record():
    """examples/emps.toml's [data] maps DATA_EMPS.mat: u = 35.15 vir, y = qm."""
    spec = loads_model((ROOT / "examples" / "emps.toml").read_text(), source="emps.toml")
    path = ROOT / "examples" / "data" / "emps" / "DATA_EMPS.mat"
    record = read_data(path, spec.layout)
    variables = scipy.io.loadmat(path)
    np.testing.assert_allclose(record.u[:, 0], 35.15 * variables["vir"].ravel(), rtol=EXACT)
    np.testing.assert_array_equal(record.y[:, 0], variables["qm"].ravel())


def test_cli_estimate_reads_a_mat_file_through_the_mapping(tmp_path, capsys):
    """``thetahat estimate MODEL FILE.mat``: the same θ̂ as the API on the mapped arrays."""
    from thetahat.cli import main
    from thetahat.modelfile import run_estimator

    n = 200
    rng = np.random.default_rng(7)
    t = np.arange(n) * 0.01
    volts, pos_mm = np.sin(t), 100 * rng.normal(size=n) * 0.01
    model = tmp_path / "m.toml"
    model.write_text(MAPPED)
    path = tmp_path / "log.mat"
    scipy.io.savemat(path, {"time": t, "volts": volts, "pos_mm": pos_mm})
    out = tmp_path / "est.csv"
    assert main(["estimate", str(model), str(path), "-o", str(out), "--no-progress"]) == 0
    assert f"({n} rows)" in capsys.readouterr().out
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    column = out.read_text().splitlines()[0].split(",").index("theta_hat_theta")
    spec = loads_model(MAPPED)
    api = run_estimator(spec, t, (35.15 * volts - 1.5)[:, None], (1e-3 * pos_mm)[:, None])
    np.testing.assert_allclose(table[:, column], api.theta_hat[:, 0], rtol=1e-12, atol=1e-15)


def test_cli_refuses_v73_and_checks_demo_output_first(tmp_path, capsys):
    from thetahat.cli import main

    model = tmp_path / "m.toml"
    model.write_text(MAPPED)
    path = tmp_path / "big.mat"
    path.write_bytes(b"MATLAB 7.3 MAT-file".ljust(512, b" ") + b"\x89HDF\r\n\x1a\n")
    assert main(["estimate", str(model), str(path), "-o", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert "v7.3" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("")
    assert main(["demo", "emps", "--out", str(blocker)]) == 2   # refused before estimating
    assert "not a writable folder" in capsys.readouterr().err


def test_list_of_signals_for_several_inputs(tmp_path):
    two_inputs = (EXAMPLE_MODEL.replace("B = [[0.0], [1.0]]", "B = [[0.0, 0.0], [1.0, 1.0]]")
                  .replace('u = ["u"]', 'u = ["u", "w"]'))
    spec = loads_model(two_inputs + '[data]\nt = "time"\n'
                       'u = ["a", { column = "b", scale = 2.0 }]\ny = "pos"\n')
    path = tmp_path / "two.mat"
    scipy.io.savemat(path, {"time": [0.0, 1.0], "a": [1.0, 2.0], "b": [3.0, 4.0],
                            "pos": [0.5, 0.6]})
    record = read_data(path, spec.layout)
    assert record.u.tolist() == [[1.0, 6.0], [2.0, 8.0]]
    assert record.columns == ("time", "a", "b", "pos")


def test_output_dropouts_follow_the_nan_policy(tmp_path):
    raw = _record()
    raw["pos_mm"][5] = np.nan
    path = tmp_path / "gap.mat"
    scipy.io.savemat(path, raw)
    spec = loads_model(MAPPED)
    assert np.isnan(read_data(path, spec.layout, nan_policy="skip").y[5, 0])
    with pytest.raises(ModelFileError, match=r"sample 5, variable 'pos_mm': nan .*--nan-policy skip"):
        read_data(path, spec.layout)
