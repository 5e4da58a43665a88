"""Input signals: values against their formulas, derivatives against finite differences,
shapes, jumps, grids and error paths."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from thetahat.errors import DimensionError, NonFiniteError
from thetahat.simulation.signals import FromArray, Multisine, Steps, time_grid

#: Same formula evaluated two ways (vectorised vs written out): only round-off differs.
SAME_FORMULA_RTOL = 1e-12
#: Central difference with h = 1e-6 s on signals with |u'''| <= ~1e3: truncation h²|u'''|/6
#: ~ 1e-10, round-off ~ 1e-16/1e-6 = 1e-10; 1e-7 leaves ample margin.
FD_ATOL = 1e-7
FD_STEP = 1e-6


def test_multisine_matches_formula_single_channel(rng):
    u = Multisine([0.7, 0.25], [0.5, 1.3])
    t = rng.uniform(0.0, 20.0, 50)
    expected = 0.7 * np.sin(2 * np.pi * 0.5 * t) + 0.25 * np.sin(2 * np.pi * 1.3 * t)
    assert u.dim == 1
    np.testing.assert_allclose(u(t)[:, 0], expected, rtol=SAME_FORMULA_RTOL, atol=1e-15)


def test_multisine_multichannel_phases_offset(rng):
    amps = np.array([[1.0, 0.5], [2.0, 0.0]])
    freqs = [0.2, 3.0]                     # shared by both channels (broadcast)
    phases = np.array([[0.1, -0.4], [1.0, 0.0]])
    u = Multisine(amps, freqs, phases, offset=[0.5, -1.0])
    t = rng.uniform(-1.0, 5.0, 30)
    ch0 = 0.5 + np.sin(2 * np.pi * 0.2 * t + 0.1) + 0.5 * np.sin(2 * np.pi * 3.0 * t - 0.4)
    ch1 = -1.0 + 2.0 * np.sin(2 * np.pi * 0.2 * t + 1.0)
    np.testing.assert_allclose(u(t), np.column_stack([ch0, ch1]), rtol=SAME_FORMULA_RTOL,
                               atol=1e-14)
    assert u.dim == 2


@pytest.mark.parametrize("t, shape", [(0.3, (1,)), (np.zeros(7), (7, 1)),
                                      (np.zeros((2, 3)), (2, 3, 1))])
def test_signal_output_shapes(t, shape):
    for sig in (Multisine([1.0], [1.0]), Steps([1.0], [2.0]), FromArray([0.0, 1.0], [0.0, 1.0])):
        assert sig(t).shape == shape
        assert sig.derivative(t).shape == shape


def test_multisine_derivative_matches_finite_difference(rng):
    u = Multisine([[0.7, 0.25], [0.1, 0.3]], [[0.5, 1.3], [2.0, 0.7]], [[0.0, 1.0], [0.5, 0.0]])
    t = rng.uniform(0.0, 10.0, 40)
    fd = (u(t + FD_STEP) - u(t - FD_STEP)) / (2 * FD_STEP)
    np.testing.assert_allclose(u.derivative(t), fd, atol=FD_ATOL)


def test_steps_right_continuous_with_initial_level():
    u = Steps([1.0, 2.0, 4.0], [[0.5, 1.0], [-0.5, 2.0], [0.0, 0.0]], initial=[9.0, 8.0])
    t = np.array([0.0, 0.999, 1.0, 1.5, 2.0, 3.999, 4.0, 100.0])
    expected = np.array([[9, 8], [9, 8], [0.5, 1], [0.5, 1], [-0.5, 2], [-0.5, 2], [0, 0],
                         [0, 0]], dtype=float)
    np.testing.assert_array_equal(u(t), expected)
    assert u.breakpoints == (1.0, 2.0, 4.0)
    np.testing.assert_array_equal(u.derivative(t), np.zeros_like(expected))


def test_from_array_zoh_and_foh():
    t = np.array([0.0, 1.0, 3.0])
    vals = np.array([1.0, 3.0, -1.0])
    zoh, foh = FromArray(t, vals), FromArray(t, vals, hold="foh")
    tq = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 7.0])
    np.testing.assert_array_equal(zoh(tq)[:, 0], [1.0, 1.0, 1.0, 3.0, 3.0, -1.0, -1.0])
    np.testing.assert_allclose(foh(tq)[:, 0], np.interp(tq, t, vals), rtol=SAME_FORMULA_RTOL)
    np.testing.assert_allclose(foh.derivative(tq)[:, 0], [0.0, 2.0, 2.0, -2.0, -2.0, 0.0, 0.0])
    assert zoh.breakpoints == foh.breakpoints == (1.0, 3.0)   # jumps, kinks


def test_from_array_foh_derivative_matches_finite_difference(rng):
    t = np.sort(rng.uniform(0.0, 10.0, 25))
    sig = FromArray(t, rng.normal(size=(25, 2)), hold="foh")
    tq = rng.uniform(t[0], t[-1], 50)
    tq = tq[np.min(np.abs(tq[:, None] - t[None, :]), axis=1) > 10 * FD_STEP]  # off the kinks
    fd = (sig(tq + FD_STEP) - sig(tq - FD_STEP)) / (2 * FD_STEP)
    np.testing.assert_allclose(sig.derivative(tq), fd, atol=1e-6)


def test_time_grid_includes_end_point_despite_round_off():
    t = time_grid(20.0, 1000.0)
    assert t.size == 20001
    assert t[0] == 0.0 and t[-1] == pytest.approx(20.0, abs=1e-12)
    np.testing.assert_allclose(np.diff(t), 1e-3, rtol=1e-9)
    assert time_grid(1.0, 3.0, t0=0.5).tolist() == pytest.approx([0.5, 0.5 + 1 / 3])


def test_sampled_returns_sample_matrix():
    u = Multisine([1.0], [1.0])
    t = time_grid(1.0, 8.0)
    np.testing.assert_array_equal(u.sampled(t), u(t))
    assert u.sampled(t).shape == (9, 1)


def test_signals_are_frozen_and_read_only():
    u = Multisine([1.0], [1.0])
    with pytest.raises(dataclasses.FrozenInstanceError):
        u.amplitudes = np.ones((1, 1))  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        u.amplitudes[0, 0] = 2.0
    src = np.array([0.0, 1.0])
    sig = FromArray([0.0, 1.0], src)
    src[0] = 5.0                      # the signal keeps its own copy
    assert sig(0.0)[0] == 0.0


@pytest.mark.parametrize("make, exc, match", [
    (lambda: Multisine([1.0], [-1.0]), DimensionError, ">= 0 Hz"),
    (lambda: Multisine([1.0, 2.0], [1.0, 2.0, 3.0]), DimensionError, "broadcast"),
    (lambda: Multisine([np.nan], [1.0]), NonFiniteError, "amplitudes"),
    (lambda: Steps([2.0, 1.0], [0.0, 1.0]), DimensionError, "strictly increasing"),
    (lambda: Steps([1.0, 2.0], [0.0]), DimensionError, "one level per switching time"),
    (lambda: Steps([], []), DimensionError, "at least one"),
    (lambda: FromArray([0.0, 1.0], [0.0, 1.0], hold="cubic"), DimensionError, "hold"),
    (lambda: FromArray([0.0, 0.0], [0.0, 1.0]), DimensionError, "strictly increasing"),
    (lambda: FromArray([0.0, 1.0], [0.0, np.inf]), NonFiniteError, "values"),
    (lambda: time_grid(0.0, 10.0), DimensionError, "t_end - t0"),
    (lambda: time_grid(1.0, -1.0), DimensionError, "fs"),
])
def test_constructor_errors(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


def test_evaluation_errors():
    u = Multisine([1.0], [1.0])
    with pytest.raises(NonFiniteError, match="t"):
        u(float("nan"))
    with pytest.raises(NonFiniteError):
        u(np.array([0.0, np.inf]))
    with pytest.raises(DimensionError, match="non-decreasing"):
        u.sampled([1.0, 0.0])
    with pytest.raises(DimensionError, match="1-D"):
        u.sampled(np.zeros((2, 2)))
