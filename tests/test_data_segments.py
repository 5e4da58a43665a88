"""Which samples to estimate from (issue 34): [data] samples and [data.segments], read by
thetahat.io.mapping, applied by read_data, overridden by thetahat estimate --samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.errors import IndexOutOfRangeError, ModelFileError
from thetahat.io.datafile import read_data
from thetahat.io.mapping import ALL_SAMPLES, parse_data_table, select_samples
from thetahat.io.record import DataRecord
from thetahat.modelfile import keys as K, loads_model
from thetahat.studies.free_run import simulate_output

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _parse(table):
    return parse_data_table(table, ["u"], ["y"], ModelFileError)


def test_segments_and_samples_are_parsed():
    m = _parse({"samples": "fit", "segments": {"fit": [5, 50], "hold_out": [50, 80]}})
    assert m.segments == (("fit", 5, 50), ("hold_out", 50, 80))
    assert m.samples == "fit" and m.segment("hold_out") == (50, 80)
    assert _parse({}).samples == ALL_SAMPLES == K.DATA["samples"].default
    assert _parse({}).segments == () and K.DATA["segments"].default == {}
    assert _parse({"samples": [3, 9]}).samples == (3, 9)


@pytest.mark.parametrize("table, says", [
    ({"samples": "train"}, "names no segment"),
    ({"samples": "train", "segments": {"test": [0, 9]}}, "names no segment"),
    ({"segments": {"a": [5, 5]}}, "0 <= START < STOP"),
    ({"segments": {"a": [-1, 5]}}, "0 <= START < STOP"),
    ({"segments": {"a": [0.0, 5]}}, "two whole numbers"),
    ({"segments": {"a": [0, 5, 9]}}, "[START, STOP]"),
    ({"segments": {"all": [0, 5]}}, "means the whole record"),
    ({"segments": [0, 5]}, "table of names"),
    ({"samples": 3}, "segment's name"),
])
def test_bad_segments_are_refused_with_the_fix(table, says):
    with pytest.raises(ModelFileError, match=None) as err:
        _parse(table)
    assert says in str(err.value)


def test_select_samples_resolves_names_ranges_and_all():
    m = _parse({"samples": "fit", "segments": {"fit": [5, 50]}})
    assert select_samples(m, 100) == (5, 50)
    assert select_samples(m, 100, "all") == (0, 100)
    assert select_samples(m, 100, ":20") == (0, 20)
    assert select_samples(m, 100, "20:") == (20, 100)
    assert select_samples(m, 100, (1, 3)) == (1, 3)
    assert select_samples(None, 7) == (0, 7)
    for bad, says in (("1:x", "START:STOP"), ("50:10", "0 <= START < STOP"),
                      ("90:200", "go beyond its 100 samples"), ("nope", "no segment 'nope'")):
        with pytest.raises(ModelFileError, match=None) as err:
            select_samples(m, 100, bad)
        assert says in str(err.value)
    with pytest.raises(ModelFileError, match="no \\[data.segments\\]"):
        select_samples(None, 100, "fit")


def test_a_record_segment_keeps_t_and_says_where_it_came_from():
    rec = DataRecord(np.arange(10.0), np.zeros((10, 1)), np.ones((10, 1)), ("t", "u", "y"), "f")
    part = rec.segment(2, 6).segment(1, 3)
    assert part.samples == (3, 5) and part.t.tolist() == [3.0, 4.0]
    assert rec.segment(0, 10) is rec and rec.samples is None
    with pytest.raises(IndexOutOfRangeError):
        rec.segment(4, 5)


def _with_data(name: str, samples: str, segments: str) -> str:
    """A shipped model file with a samples key in its [data] table (created if absent) and a
    [data.segments] table at its end."""
    text = (EXAMPLES / f"{name}.toml").read_text(encoding="utf-8")
    if "\n[data]\n" in text:
        text = text.replace("\n[data]\n", f"\n[data]\n{samples}\n")
    else:
        text += f"\n[data]\n{samples}\n"
    return text + f"\n[data.segments]\n{segments}\n"


@pytest.mark.parametrize("name", ["heater", "spring_friction", "prop1", "emps"])
def test_read_data_returns_the_files_samples_on_shipped_models(name, tmp_path):
    """The same table on four shipped models: CSV records for three of them, the EMPS MAT
    file for the fourth; the file's samples by default, --samples' choice when given."""
    text = _with_data(name, 'samples = "fit"', "fit = [10, 60]\nrest = [60, 90]")
    spec = loads_model(text, source=f"{name}.toml")
    if name == "emps":
        path = EXAMPLES / "data" / "emps" / "DATA_EMPS.mat"
        whole = read_data(path, spec.layout, samples="all")
    else:
        N = 100
        cols = ["t"] + list(spec.input_names) + list(spec.output_names)
        data = np.column_stack([np.arange(N) * 0.01] + [np.sin(np.arange(N) * (i + 1) * 0.1)
                                                       for i in range(len(cols) - 1)])
        path = tmp_path / "rec.csv"
        np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="")
        whole = read_data(path, spec.layout, samples="all")
    fit = read_data(path, spec.layout)
    assert fit.samples == (10, 60) and fit.t.size == 50
    np.testing.assert_array_equal(fit.t, whole.t[10:60])
    np.testing.assert_array_equal(fit.y, whole.y[10:60])
    rest = read_data(path, spec.layout, samples="rest")
    np.testing.assert_array_equal(rest.u, whole.u[60:90])


def test_cli_samples_option_and_its_errors(tmp_path, capsys):
    text = _with_data("spring_friction", "", "fit = [10, 60]")
    model = tmp_path / "m.toml"
    model.write_text(text, encoding="utf-8")
    spec = loads_model(text)
    N = 200
    t = np.arange(N) * 0.01
    u = 5 * np.sin(2 * np.pi * 0.7 * t)[:, None]
    y = simulate_output(spec.system, spec.scenario.theta, t, u, x0=[0.0, 0.0])
    y += 1e-4 * np.random.default_rng(0).standard_normal(y.shape)
    np.savetxt(tmp_path / "r.csv", np.column_stack([t, u, y]), delimiter=",",
               header="t,u,y", comments="")
    out = tmp_path / "e.csv"
    base = ["estimate", str(model), str(tmp_path / "r.csv"), "-o", str(out), "--method", "ekf",
            "--no-progress"]
    assert main(base + ["--samples", "fit"]) == 0
    assert "(50 rows)" in capsys.readouterr().out
    assert main(base) == 0                                     # no samples key: all of it
    assert "(200 rows)" in capsys.readouterr().out
    assert main(base + ["--samples", "1:"]) == 0
    assert "(199 rows)" in capsys.readouterr().out
    assert main(base + ["--samples", "9:3"]) == 2
    assert "0 <= START < STOP" in capsys.readouterr().err
    fleet = ["estimate", str(model), str(tmp_path), "-o", str(tmp_path / "f.csv"),
             "--samples", "fit"]
    assert main(fleet) == 2
    assert "--samples chooses samples of one record" in capsys.readouterr().err
