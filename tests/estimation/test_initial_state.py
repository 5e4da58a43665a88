"""x̂(0) from the first output sample: x̂₀ + C⁺(y(0) − C x̂₀), one definition for every method,
the model file's switch, and a record that begins in motion."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import DimensionError, ModelFileError
from thetahat.estimation.observer.initial_state import output_pinv, x_hat_from_output
from thetahat.modelfile import load_model, loads_model, run_estimator, start_x_hat
from thetahat.modelfile.study import simulate_model

PROP3 = Path(__file__).resolve().parents[2] / "examples" / "prop3.toml"
#: Rounding of one SVD and two products of order-1 numbers.
FIT_ATOL = 1e-12
#: The prop3 scenario (θ = 1.2, seed 0) cut at its largest |y| in the second quarter
#: (y(0) = 3.75, 3.5 standard deviations of y, x̂₀ = 0) and kept for 8 s: every method ends
#: within 2 % of θ (measured 0.01 % – 0.3 %).
CUT, KEEP = 779, 800
THETA_RTOL = 0.02
#: Started at 0 the paper's observer peaks to |x̂₁| = 10.8 on this record (2.9 × max|y|);
#: started from y(0) its |x̂₁| stays within 3 % of max|y| (the noise and the observer's lag).
NO_PEAK = 1.1


def test_fit_is_the_least_squares_point_nearest_the_prior():
    rng = np.random.default_rng(5)
    C = rng.standard_normal((2, 4))                                  # full row rank
    x0, y0 = rng.standard_normal(4), rng.standard_normal(2)
    x = x_hat_from_output(C, y0, x0)
    assert np.allclose(C @ x, y0, atol=FIT_ATOL)                     # fits y(0)
    kernel = np.linalg.svd(C)[2][2:]                                 # ker C, orthonormal rows
    assert np.allclose(kernel @ (x - x0), 0.0, atol=FIT_ATOL)        # unseen part kept
    assert np.allclose(output_pinv(C) @ C @ output_pinv(C), output_pinv(C), atol=FIT_ATOL)


def test_dropout_keeps_the_prior_and_shapes_are_checked():
    C = np.array([[1.0, 0.0], [0.0, 1.0]])
    assert x_hat_from_output(C, [np.nan, 2.0], [0.5, 0.5]).tolist() == [0.5, 0.5]
    with pytest.raises(DimensionError, match="y0"):
        x_hat_from_output(C, [1.0, 2.0, 3.0])


def test_model_file_switch():
    text = PROP3.read_text()
    y = np.array([[2.0], [2.1]])
    assert start_x_hat(loads_model(text), y).tolist() == [2.0, 0.0]
    off = loads_model(text.replace("[estimator]", "[estimator]\nx_hat0_from_y = false"))
    assert start_x_hat(off, y).tolist() == [0.0, 0.0]
    with pytest.raises(ModelFileError, match="x_hat0_from_y"):
        loads_model(text.replace("[estimator]", "[estimator]\nx_hat0_from_y = 1"))


def cut_record():
    spec = load_model(PROP3)
    d = simulate_model(spec, 0)
    s = slice(CUT, CUT + KEEP)
    return spec, d.t[s] - d.t[CUT], d.u[s], d.y[s], d.theta


@pytest.mark.parametrize("method", ["paper", "guarded", "mle"])
def test_record_that_begins_in_motion(method):
    spec, t, u, y, theta = cut_record()
    assert abs(y[0, 0]) > 3 * np.std(y)                              # far from C x̂₀ = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_estimator(spec, t, u, y, method=method, diagnose=False)
    assert res.x_hat[0, 0] == pytest.approx(y[0, 0], abs=FIT_ATOL)
    assert np.all(np.abs(res.theta_hat[-1] / theta - 1) < THETA_RTOL)
    assert spec.system.parameter_set.contains(res.theta_hat).all()
    if method == "paper":
        assert np.max(np.abs(res.x_hat[:, 0])) < NO_PEAK * np.max(np.abs(y))


#: The heater started hot: T_h and T_b 300 K and 250 K above the room. x̂(0) = (300, 0) from
#: y(0); T_b is not measured and its 25-min time constant makes x(0) matter for the whole run.
HOT = "x0 = [300.0, 250.0]"
#: RMSE over the last half of 2 runs ÷ √CRLB: an efficient estimator gives ≈ 1; the RMS of two
#: standard normal draws exceeds 2.5 with probability e^(−6.25) ≈ 0.2 % per parameter.
#: Measured 1.11 / 1.17; with a prior sd of 10 K on x(0) around x̂(0) (absolute, as before
#: x_prior_sd) 8.2 / 3.2: the prior held T_b(0) near 0 against 250 K (the test after next).
HOT_BOUND = 2.5


def _hot_heater():
    text = (PROP3.parent / "heater.toml").read_text()
    assert "x0 = [0.0, 0.0]" in text
    return loads_model(text.replace("x0 = [0.0, 0.0]", HOT))


def _last_half_ratio(spec, run):
    """RMSE over the last half of seeds 0 and 1 ÷ √(mean CRLB there); θ̂ finite and in Θ."""
    import thetahat
    sc = spec.scenario
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    errs, var = [], None
    for seed in range(2):
        d = simulate_model(spec, seed)
        U, Y, N = np.asarray(d.u), np.asarray(d.y), d.t.size
        if var is None:
            b = thetahat.crlb(spec.system, d.t, U, theta=sc.theta, noise_std=sc.noise_std,
                              x0=sc.x0, x0_known=False)
            var = np.mean(np.diagonal(np.asarray(b.cov), axis1=-2, axis2=-1)[N // 2:], axis=0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            th = np.asarray(run(d.t, U, Y).theta_hat)
        assert np.all(np.isfinite(th)) and np.all((th >= lo) & (th <= hi))
        errs.append(th[N // 2:] - sc.theta)
    return np.sqrt(np.mean(np.concatenate(errs) ** 2, axis=0) / var)


@pytest.mark.parametrize("method", ["mle", "guarded"])
@pytest.mark.needs_speed
def test_prior_of_x0_scales_with_the_start(method):
    """The prior of x(0) is wide against the start's magnitude (common.x_prior_sd): a process
    that starts far from its reference in an unmeasured state is estimated at the bound."""
    spec = _hot_heater()
    ratio = _last_half_ratio(spec, lambda t, U, Y: run_estimator(spec, t, U, Y, method=method,
                                                                 diagnose=False))
    assert np.all(ratio < HOT_BOUND), ratio


@pytest.mark.needs_speed
def test_an_absolute_prior_of_x0_misses_the_hot_start():
    """The same record with the fits' prior of x(0) fixed at ± 10 (X_PRIOR_SD in the state's
    units, the default before x_prior_sd): the bound above is missed — what the derived
    default is for (measured 8.2 / 3.2)."""
    import dataclasses

    from thetahat.estimation.statistical.common import X_PRIOR_SD
    from thetahat.estimation.statistical.map_fit import FitSchedule
    from thetahat.modelfile import build_estimator
    spec = _hot_heater()
    est = build_estimator(spec, method="mle")
    est = dataclasses.replace(est, schedule=FitSchedule(system=spec.system, x_sd=X_PRIOR_SD))

    def run(t, U, Y):
        return est.run(t, U, Y, state0=est.init(x_hat0=start_x_hat(spec, Y),
                                                theta_hat0=spec.estimator.theta_hat0))
    assert np.any(_last_half_ratio(spec, run) > HOT_BOUND)


def test_x_prior_sd_given_or_derived():
    from thetahat.errors import OptionError
    from thetahat.estimation.statistical.common import X_PRIOR_SD, x_prior_sd
    assert np.array_equal(x_prior_sd(np.zeros(3)), np.full(3, X_PRIOR_SD))
    assert np.array_equal(x_prior_sd([0.5, -40.0]), np.full(2, 40.0 * X_PRIOR_SD))
    assert np.array_equal(x_prior_sd([0.5, -40.0], 2.0), [2.0, 2.0])      # given: as is
    assert np.array_equal(x_prior_sd([0.5, -40.0], [1.0, 3.0]), [1.0, 3.0])
    with pytest.raises(OptionError, match="positive"):
        x_prior_sd([0.0, 0.0], [1.0, 0.0])
    with pytest.raises(DimensionError, match="one per"):
        x_prior_sd([0.0, 0.0], [1.0, 2.0, 3.0])
