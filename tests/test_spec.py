"""The estimator spec: one place that assembles observers, one SCB per design family."""

from __future__ import annotations

import functools
import pickle
from pathlib import Path

import numpy as np
import pytest

from thetahat import (ConstantLaw, DimensionError, EstimatorSpec, ModelFileError,
                      SecondObserverSpec, UpdateLawError, high_gain, modified_high_gain)
from thetahat.design import gains
from thetahat.modelfile import EXAMPLE_MODEL, estimator_spec, loads_model
from thetahat.models import lugre, prop3_monotone
from thetahat.studies.sweep import eps_sweep
from thetahat.studies.tune import tune_eps_gamma

#: K from the spec and from a direct design: the same arithmetic on the same SCB, so they
#: agree to rounding amplified by ‖K‖ ~ ε^−3; 1e-9 of ‖K‖ is far above that.
K_RTOL = 1e-9
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
EPS_10 = (1.0, 0.8, 0.6, 0.5, 0.4, 0.3, 0.2, 0.15, 0.1, 0.05)


def _count_scb(monkeypatch):
    count = [0]
    original = gains.scb

    def wrapped(*args, **kwargs):
        count[0] += 1
        return original(*args, **kwargs)

    monkeypatch.setattr(gains, "scb", wrapped)
    return count


def test_lugre_spec_is_the_papers_design():
    """Sec. VIII: K ≈ [6, 0, 6]ᵀ and K2 ≈ [3, 0]ᵀ on the σ1 = 0 design system, for any ε
    equal to a design made directly at that ε."""
    spec = lugre.estimator_spec()
    ds = lugre.design_system()
    for eps in (1.0, 0.3, 0.05):
        obs = spec.build(eps=eps)
        direct = modified_high_gain(ds.A, ds.E, ds.C, eps, [[-1.0, -2.0, -3.0]])
        scale = np.linalg.norm(direct.K)
        np.testing.assert_allclose(np.vstack([obs.K_x, obs.K_phi]), direct.K, rtol=0,
                                   atol=K_RTOL * scale)
    d2 = high_gain(ds.A, ds.E, ds.C, 1.0, [[-1.0, -2.0]])
    np.testing.assert_allclose(spec.design2.K, d2.K, rtol=K_RTOL)
    np.testing.assert_allclose(spec.design.K.ravel(), [6.0, -0.0041588, 6.0075], rtol=1e-3,
                               atol=1e-6)


def test_build_replaces_gamma_and_keeps_the_law():
    spec = lugre.estimator_spec()
    obs = spec.build(eps=0.5, Gamma=7.0)
    assert obs.update_law.Gamma.tolist() == [[7.0]]
    assert type(obs.update_law) is type(spec.law)
    assert obs.update_law.on_invalid == spec.law.on_invalid == "freeze"
    assert spec.law.Gamma.tolist() == [[1.0]]                   # the spec is unchanged
    assert spec.build().update_law is spec.law
    with pytest.raises(UpdateLawError, match="positive"):
        spec.build(Gamma=-1.0)


def test_an_eps_sweep_of_ten_values_costs_one_scb(monkeypatch):
    """Issue 10: K(ε) for every ε of a sweep comes from one SCB (plus one for the second
    observer's fixed gain), where a redesign per run cost two SCBs for each (ε, seed)."""
    count = _count_scb(monkeypatch)
    spec = lugre.estimator_spec()
    assert count[0] == 2                                       # K(ε) family + second observer
    sim = functools.lru_cache(maxsize=None)(functools.partial(lugre.simulate, t_end=0.05))
    res = eps_sweep(spec, sim, EPS_10, seeds=[0], theta_hat0=[0.5], progress=False)
    assert count[0] == 2 and len(res.eps) == 10
    eps_sweep(lugre.observer, sim, EPS_10, seeds=[0], theta_hat0=[0.5], progress=False)
    assert count[0] == 2 + 2 * len(EPS_10)                    # the per-run redesign it replaces


def test_spec_and_callable_give_the_same_sweep():
    sim = functools.lru_cache(maxsize=None)(functools.partial(lugre.simulate, t_end=0.3))
    a = eps_sweep(lugre.estimator_spec(), sim, [1.0, 0.5], seeds=[0], theta_hat0=[0.5],
                  progress=False)
    b = eps_sweep(lugre.observer, sim, [1.0, 0.5], seeds=[0], theta_hat0=[0.5],
                  progress=False)
    np.testing.assert_array_equal(a.theta_rmse, b.theta_rmse)
    np.testing.assert_array_equal(a.x_rmse, b.x_rmse)


def test_tune_builds_every_pair_from_one_spec(monkeypatch):
    spec = prop3_spec()
    count = _count_scb(monkeypatch)
    sim = functools.partial(_prop3_data, t_end=1.0)
    res = tune_eps_gamma(spec, sim, eps_values=[1.0, 0.5], gammas=[1.0, 4.0], seeds=[1],
                         theta_hat0=[0.0])
    assert count[0] == 0 and res.score.shape == (2, 2)
    assert np.isfinite(res.score).all()


def prop3_spec(**kw):
    return EstimatorSpec(system=prop3_monotone.system(), law=prop3_monotone.update_law(), **kw)


def _prop3_data(seed, t_end):
    from thetahat.modelfile.study import simulate_model
    return simulate_model(loads_model(EXAMPLE_MODEL), seed, t_end=t_end)


def test_spec_runs_with_its_hold():
    data = _prop3_data(0, 1.0)
    for hold in ("zoh", "foh"):
        res = prop3_spec(hold=hold).run(data.t, data.u, data.y)
        built = prop3_spec(hold=hold).build()
        assert built.hold == hold                         # the spec's hold is the observer's
        ref = prop3_spec().build().with_run_options(hold=hold).run(data.t, data.u, data.y)
        np.testing.assert_array_equal(res.theta_hat, ref.theta_hat)


def test_spec_pickles_for_worker_processes():
    """eps_sweep(n_jobs > 1) sends the spec and simulate(seed) to worker processes."""
    from thetahat.modelfile import load_model, study_simulator
    spec = lugre.estimator_spec()
    back = pickle.loads(pickle.dumps(spec))
    np.testing.assert_array_equal(back.design.K, spec.design.K)
    assert repr(back) == repr(spec)
    v, x, phi = np.array([0.0, 2.0]), np.array([2.0, 1e-3]), np.array([1.0])
    np.testing.assert_array_equal(back.law.theta_star(v, x, phi), spec.law.theta_star(v, x, phi))
    model = load_model(EXAMPLES / "prop3.toml")
    pickle.loads(pickle.dumps(estimator_spec(model)))
    sim = pickle.loads(pickle.dumps(study_simulator(model, t_end=0.1)))
    assert sim(0).y.shape == (11, 1)


def test_bad_specs_are_refused():
    with pytest.raises(DimensionError, match="hold must be one of"):
        prop3_spec(hold="cubic")
    with pytest.raises(UpdateLawError, match="must be an UpdateLaw"):
        EstimatorSpec(system=prop3_monotone.system(), law=lambda *a: 0)
    with pytest.raises(DimensionError, match="same sizes"):
        prop3_spec(design_system=lugre.design_system().__class__(
            A=np.zeros((3, 3)), B=np.zeros((3, 1)), C=np.eye(1, 3), E=np.ones((3, 1))))
    const = EstimatorSpec(system=prop3_monotone.system(),
                          law=ConstantLaw([0.0], prop3_monotone.PARAMETER_SET))
    with pytest.raises(UpdateLawError, match="has no adaptation gain"):
        const.build(Gamma=2.0)
    with pytest.raises(DimensionError, match="g_on_estimates"):
        SecondObserverSpec(g_on_estimates="yes")


def test_model_file_errors_name_the_design_that_failed():
    bad_second = EXAMPLE_MODEL.replace("eps2 = 1.0", "eps2 = 1.0\nchain_poles = [[-1.0]]")
    with pytest.raises(ModelFileError, match=r"\[estimator.second\].*2 poles"):
        estimator_spec(loads_model(bad_second))
    bad_first = EXAMPLE_MODEL.replace("eps = 0.5", "eps = 0.5\nchain_poles = [[-1.0]]")
    with pytest.raises(ModelFileError, match=r"\[estimator\] eps/chain_poles.*3 poles"):
        estimator_spec(loads_model(bad_first))
