"""The registry of estimation methods: one list, read by the model file, the API, the shipped
model and the command line, and the names written nowhere else."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import thetahat
from thetahat.cli import main
from thetahat.errors import ModelFileError, OptionError
from thetahat.estimation.protocol import Estimator
from thetahat.methods import ESTIMATION_METHODS, METHODS, MethodInputs, get_method, method_help
from thetahat.modelfile import EXAMPLE_MODEL, build_estimator, load_model, loads_model
from thetahat.modelfile.keys import ESTIMATOR
from thetahat.models import lugre

SRC = Path(thetahat.__file__).resolve().parent
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: Three shipped models besides LuGre, of different sizes (n, m, p) and laws.
MODELS = ("prop1.toml", "two_inertia.toml", "heater.toml")

#: The estimator type each method builds for a model file (the paper's observer carries its
#: hold itself).
TYPES = {"paper": "ModifiedHighGainObserver", "guarded": "GuardedEstimator", "mle": "MapEstimator",
         "ekf": "JointEKF"}


def test_the_registry_is_one_ordered_list_of_distinct_methods():
    assert ESTIMATION_METHODS == tuple(m.name for m in METHODS)
    assert len(set(ESTIMATION_METHODS)) == len(METHODS) == len(TYPES)
    assert set(ESTIMATION_METHODS) == set(TYPES)
    for m in METHODS:
        assert get_method(m.name) is m and m.description and m.description in method_help()
    assert [m.name for m in METHODS if m.runs_observer] == ["guarded", "paper"]
    assert ESTIMATION_METHODS[0] == "guarded"        # the default: guaranteed and efficient


def _literal_name_lists(path: Path) -> list[int]:
    """Lines of ``path`` holding a literal tuple/list/set with every method name."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            names = {e.value for e in node.elts if isinstance(e, ast.Constant)}
            if set(ESTIMATION_METHODS) <= names:
                found.append(node.lineno)
    return found


def test_the_names_are_listed_once_in_the_package():
    """No literal list of the method names outside :mod:`thetahat.methods` (the schema, the
    LuGre model and the command line each had one)."""
    where = {str(p.relative_to(SRC)): _literal_name_lists(p) for p in SRC.rglob("*.py")}
    assert {p: lines for p, lines in where.items() if lines} == {}


def test_the_finder_finds_a_literal_list(tmp_path):
    path = tmp_path / "m.py"
    path.write_text(f"X = {list(ESTIMATION_METHODS)!r}\nY = ('paper', 'mle')\n")
    assert _literal_name_lists(path) == [1]


def test_every_reader_takes_its_choices_from_the_registry(capsys):
    assert ESTIMATOR["method"].choices == ESTIMATION_METHODS          # the model file
    assert ESTIMATOR["method"].default == ESTIMATION_METHODS[0]
    assert main(["estimate", "--help"]) == 0                          # --method
    text = " ".join(capsys.readouterr().out.split())
    assert "--method {" + ",".join(ESTIMATION_METHODS) + "}" in text
    for m in METHODS:
        assert f"{m.name}: {m.description}" in text


@pytest.mark.parametrize("name", MODELS)
def test_each_method_builds_from_a_shipped_model_file(name):
    spec = load_model(EXAMPLES / name)
    for method in ESTIMATION_METHODS:
        est = build_estimator(spec, method=method, compiled=False,
                              Gamma=np.eye(spec.system.p) if spec.estimator.gamma_auto else None)
        assert isinstance(est, Estimator)
        assert type(est).__name__ == TYPES[method]


def test_each_method_builds_for_lugre():
    assert type(lugre.estimator("paper")).__name__ == "ModifiedHighGainObserver"
    for method in ("guarded", "mle", "ekf"):
        est = lugre.estimator(method, compiled=False)
        assert type(est).__name__ == TYPES[method] and est.system.p == 1


def test_statistical_methods_never_build_the_observer():
    """"mle" and "ekf" need no gains: the observer callable is not called."""
    def observer():
        raise AssertionError("the observer was built")
    inputs = MethodInputs(system=lugre.system(), observer=observer, compiled=False)
    assert type(get_method("mle").build(inputs)).__name__ == "MapEstimator"
    assert type(get_method("ekf").build(inputs)).__name__ == "JointEKF"
    with pytest.raises(AssertionError, match="was built"):
        get_method("paper").build(inputs)


def test_an_unknown_method_is_refused_by_every_reader():
    spec = loads_model(EXAMPLE_MODEL)
    for call in (lambda: lugre.estimator("ukf"),
                 lambda: build_estimator(spec, method="ukf"),
                 lambda: get_method("ukf")):
        with pytest.raises(OptionError, match=r"unknown method 'ukf'; expected one of \["
                                              r"'guarded', 'paper', 'mle', 'ekf'\]"):
            call()
    with pytest.raises(ModelFileError, match=r"\[estimator\] method: unknown method 'ukf'"):
        loads_model(EXAMPLE_MODEL.replace('law = "gradient"', 'method = "ukf"\nlaw = "gradient"'))
    assert main(["estimate", "m.toml", "d.csv", "--method", "ukf"]) == 2    # argparse's usage
