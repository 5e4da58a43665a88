"""PerturbedLinearSystem, model (1): validation once on construction, frozen read-only data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import sympy as sp

from thetahat.errors import DimensionError, NonFiniteError
from thetahat.model.paramset import ParameterSet
from thetahat.model.perturbation import CallablePerturbation, SymbolicPerturbation
from thetahat.model.system import PerturbedLinearSystem


class _Interval(ParameterSet):
    """A stand-in Θ of any dimension, independent of the concrete sets in paramset.py."""

    def __init__(self, p: int) -> None:
        self._p = p

    @property
    def dim(self) -> int:
        return self._p

    def contains(self, theta, *, tol=0.0):
        return True

    def nearest(self, theta, *, metric=None):
        return np.asarray(theta, dtype=np.float64)


@pytest.fixture
def matrices(dc_motor):
    A, B, E, C = dc_motor.linear()
    return {"A": A, "B": B, "C": C, "E": E}


@pytest.fixture(scope="module")
def lugre_g(dc_motor) -> SymbolicPerturbation:
    u, y, omega, eta, a0 = sp.symbols("u y omega eta alpha0")
    zeta = a0 + dc_motor.alpha1 * sp.exp(-((omega / dc_motor.omega0) ** 2))
    return SymbolicPerturbation.from_sympy(dc_motor.sigma0 * eta * sp.Abs(y) / zeta, u=[u],
                                           y=[y], x=[omega, eta], theta=[a0])


def test_lugre_system_dimensions(matrices, lugre_g):
    system = PerturbedLinearSystem(**matrices, perturbation=lugre_g,
                                   parameter_set=_Interval(1))
    assert (system.n, system.m, system.r, system.k, system.p) == (2, 1, 1, 1, 1)
    assert "n=2, m=1, r=1, k=1, p=1" in repr(system)
    assert "SymbolicPerturbation" in repr(system)


@pytest.mark.parametrize("name,value,match", [
    ("A", np.ones((2, 3)), r"A must be square"),
    ("A", np.ones(2), r"A must be a 2-D matrix"),
    ("B", np.ones((3, 1)), r"B must have shape \(2, \?\); got \(3, 1\)"),
    ("B", np.ones(2), r"B must be 2-D of shape \(2, \?\)"),
    ("C", np.ones((1, 3)), r"C must have shape \(\?, 2\); got \(1, 3\)"),
    ("C", np.ones(2), r"C must be 2-D of shape \(\?, 2\)"),
    ("E", np.ones((3, 1)), r"E must have shape \(2, \?\); got \(3, 1\)"),
    ("E", np.ones((2, 0)), r"E must have at least one column"),
    ("E", np.ones((2, 1), dtype=complex), r"E must be real"),
])
def test_wrong_shapes_name_the_matrix_and_the_expected_shape(matrices, name, value, match):
    with pytest.raises(DimensionError, match=match):
        PerturbedLinearSystem(**{**matrices, name: value})


@pytest.mark.parametrize("name", ["A", "B", "C", "E"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_entries_raise(matrices, name, bad):
    M = np.array(matrices[name], dtype=np.float64)
    M[-1, 0] = bad
    with pytest.raises(NonFiniteError, match=rf"^{name} contains NaN or inf"):
        PerturbedLinearSystem(**{**matrices, name: M})


@pytest.mark.parametrize("dims", [
    {"n": 3, "m": 1, "r": 1, "k": 1},
    {"n": 2, "m": 2, "r": 1, "k": 1},
    {"n": 2, "m": 1, "r": 2, "k": 1},
    {"n": 2, "m": 1, "r": 1, "k": 2},
])
def test_perturbation_dims_must_agree_with_the_matrices(matrices, dims):
    g = CallablePerturbation(g=lambda v, x, th: np.zeros(x.shape[:-1] + (dims["k"],)), p=1,
                             **dims)
    with pytest.raises(DimensionError, match="perturbation dims .* disagree with the matrices"):
        PerturbedLinearSystem(**matrices, perturbation=g)


def test_parameter_set_dimension_must_equal_p(matrices, lugre_g):
    with pytest.raises(DimensionError, match="parameter_set has dimension 2 .* p = 1"):
        PerturbedLinearSystem(**matrices, perturbation=lugre_g, parameter_set=_Interval(2))


def test_perturbation_must_be_a_perturbation(matrices):
    with pytest.raises(DimensionError, match="must be a thetahat Perturbation"):
        PerturbedLinearSystem(**matrices, perturbation=lambda v, x, th: x)


def test_parameter_set_must_be_a_parameter_set(matrices, lugre_g):
    with pytest.raises(DimensionError, match="must be a thetahat ParameterSet"):
        PerturbedLinearSystem(**matrices, perturbation=lugre_g, parameter_set=(0.05, 1.0))


def test_arrays_are_read_only_copies(matrices):
    A = np.array(matrices["A"])
    system = PerturbedLinearSystem(**{**matrices, "A": A})
    A[0, 0] = 99.0  # mutating the caller's array must not reach the model
    assert system.A[0, 0] == matrices["A"][0, 0]
    for name in ("A", "B", "C", "E"):
        arr = getattr(system, name)
        assert arr.dtype == np.float64 and not arr.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            arr[0, 0] = 1.0


def test_system_is_frozen_and_keyword_only(matrices):
    system = PerturbedLinearSystem(**matrices)
    with pytest.raises(dataclasses.FrozenInstanceError):
        system.A = np.eye(2)
    with pytest.raises(TypeError):
        PerturbedLinearSystem(matrices["A"], matrices["B"], matrices["C"], matrices["E"])


def test_no_inputs_is_allowed():
    system = PerturbedLinearSystem(A=[[0.0, 1.0], [0.0, 0.0]], B=np.zeros((2, 0)),
                                   C=[[1.0, 0.0]], E=[[0.0], [1.0]])
    assert (system.m, system.p) == (0, 0)
