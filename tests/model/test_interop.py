"""Adapters to python-control and scipy.signal: matrices survive, D ≠ 0 and dt ≠ 0 are refused."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from thetahat.errors import DimensionError
from thetahat.model.interop import from_state_space, to_state_space
from thetahat.model.parse import parse_perturbation
from thetahat.model.system import PerturbedLinearSystem

control = pytest.importorskip("control")


def random_mimo(rng: np.random.Generator, n: int = 4, m: int = 2, r: int = 2, k: int = 2):
    return (rng.normal(size=(n, n)), rng.normal(size=(n, m)), rng.normal(size=(r, n)),
            rng.normal(size=(n, k)))


def assert_same_linear_part(system: PerturbedLinearSystem, A, B, C, E) -> None:
    # The adapters copy matrices; nothing is recomputed, so equality is exact.
    np.testing.assert_array_equal(system.A, A)
    np.testing.assert_array_equal(system.B, B)
    np.testing.assert_array_equal(system.C, C)
    np.testing.assert_array_equal(system.E, E)


@pytest.mark.parametrize("make", [
    lambda A, B, C: control.ss(A, B, C, np.zeros((C.shape[0], B.shape[1]))),
    lambda A, B, C: signal.StateSpace(A, B, C, np.zeros((C.shape[0], B.shape[1]))),
    lambda A, B, C: signal.lti(A, B, C, np.zeros((C.shape[0], B.shape[1]))),
], ids=["control.ss", "scipy.StateSpace", "scipy.lti"])
def test_from_state_space_reproduces_mimo_matrices(rng, make):
    A, B, C, E = random_mimo(rng)
    system = from_state_space(make(A, B, C), E=E)
    assert isinstance(system, PerturbedLinearSystem)
    assert (system.n, system.m, system.r, system.k) == (4, 2, 2, 2)
    assert_same_linear_part(system, A, B, C, E)


def test_from_state_space_lugre_motor_with_perturbation(dc_motor):
    A, B, E, C = dc_motor.linear()
    g = parse_perturbation("sigma0*eta*Abs(y)/(alpha0 + alpha1*exp(-(omega/omega0)**2))",
                           u=["u"], y=["y"], x=["omega", "eta"], theta=["alpha0"],
                           constants={"sigma0": dc_motor.sigma0, "alpha1": dc_motor.alpha1,
                                      "omega0": dc_motor.omega0})
    system = from_state_space(control.ss(A, B, C, 0), E=E, perturbation=g)
    assert system.perturbation is g and system.p == 1
    assert_same_linear_part(system, A, B, C, E)


@pytest.mark.parametrize("make", [
    lambda A, B, C: control.ss(A, B, C, [[0.0, 0.5]]),
    lambda A, B, C: signal.StateSpace(A, B, C, [[0.0, 0.5]]),
], ids=["control", "scipy"])
def test_nonzero_feedthrough_is_refused(make):
    A, B, C = np.array([[0.0, 1.0], [-1.0, -1.0]]), np.eye(2), np.array([[1.0, 0.0]])
    with pytest.raises(DimensionError, match=r"D must be zero.*y = C x \(1b\).*y - D u"):
        from_state_space(make(A, B, C), E=[[0.0], [1.0]])


@pytest.mark.parametrize("make", [
    lambda: control.ss([[0.5]], [[1.0]], [[1.0]], 0, dt=0.1),
    lambda: signal.StateSpace([[0.5]], [[1.0]], [[1.0]], [[0.0]], dt=0.1),
], ids=["control", "scipy"])
def test_discrete_time_is_refused(make):
    with pytest.raises(DimensionError, match="discrete-time.*continuous-time"):
        from_state_space(make(), E=[[1.0]])


@pytest.mark.parametrize("sys_,match", [
    (signal.lti([1.0], [1.0, 2.0]), "to_ss"),
    (None, "python-control StateSpace or a scipy"),
    (np.eye(2), "PerturbedLinearSystem"),
], ids=["scipy-tf", "none", "ndarray"])
def test_non_state_space_objects_are_refused(sys_, match):
    with pytest.raises(DimensionError, match=match):
        from_state_space(sys_, E=[[1.0]])


def test_control_transfer_function_is_refused():
    with pytest.raises(DimensionError, match=r"control.ss\(sys\)"):
        from_state_space(control.tf([1.0], [1.0, 2.0]), E=[[1.0]])


def test_wrong_E_is_reported_by_the_system(rng):
    A, B, C, _ = random_mimo(rng)
    with pytest.raises(DimensionError, match=r"E must have shape \(4, \?\)"):
        from_state_space(signal.StateSpace(A, B, C, np.zeros((2, 2))), E=np.ones((3, 1)))


@pytest.mark.parametrize("library", ["scipy", "control"])
def test_to_state_space_returns_linear_part_with_phi_as_input(rng, library):
    A, B, C, E = random_mimo(rng, n=3, m=1, r=2, k=2)
    lin = to_state_space(PerturbedLinearSystem(A=A, B=B, C=C, E=E), library=library)
    np.testing.assert_array_equal(lin.A, A)
    np.testing.assert_array_equal(lin.B, np.hstack([B, E]))
    np.testing.assert_array_equal(lin.C, C)
    np.testing.assert_array_equal(lin.D, np.zeros((2, 3)))
    back = from_state_space(lin, E=E)  # D = 0 and continuous time, so it is accepted
    np.testing.assert_array_equal(back.B, np.hstack([B, E]))


def test_to_state_space_control_names_inputs_and_is_continuous(rng):
    A, B, C, E = random_mimo(rng, n=3, m=1, r=1, k=2)
    lin = to_state_space(PerturbedLinearSystem(A=A, B=B, C=C, E=E), library="control")
    assert lin.input_labels == ["u[0]", "phi[0]", "phi[1]"]
    assert lin.output_labels == ["y[0]"]
    assert lin.isctime(strict=True)


def test_to_state_space_output_is_independent_of_the_system(rng):
    A, B, C, E = random_mimo(rng, n=2, m=1, r=1, k=1)
    system = PerturbedLinearSystem(A=A, B=B, C=C, E=E)
    lin = to_state_space(system)
    lin.A[0, 0] = 123.0  # scipy objects are mutable; the frozen system must not change
    np.testing.assert_array_equal(system.A, A)


def test_to_state_space_errors(rng):
    A, B, C, E = random_mimo(rng, n=2, m=1, r=1, k=1)
    with pytest.raises(DimensionError, match="library must be 'scipy' or 'control'"):
        to_state_space(PerturbedLinearSystem(A=A, B=B, C=C, E=E), library="harold")
    with pytest.raises(DimensionError, match="must be a PerturbedLinearSystem"):
        to_state_space(signal.StateSpace(A, B, C, [[0.0]]))


def test_interop_imports_control_and_scipy_lazily():
    """No module-level import of the adapters' libraries (python-control is optional)."""
    import thetahat.model.interop as interop

    tree = ast.parse(Path(interop.__file__).read_text(encoding="utf-8"))
    top_level = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            top_level.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            top_level.add(node.module.split(".")[0])
    assert {"control", "scipy"}.isdisjoint(top_level)
    assert "numpy" in top_level  # the walk does see module-level imports
