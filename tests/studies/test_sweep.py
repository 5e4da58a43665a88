"""ε sweeps (Sec. VII): bookkeeping of divergence and metrics, validation, the LuGre example."""

from __future__ import annotations

import functools
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from thetahat.errors import DesignError, DimensionError, NonFiniteError
from thetahat.models import lugre
from thetahat.studies.sweep import SweepResult, eps_sweep

#: ω ranges over about ±3.8 rad/s in the default scenario; an observer that tracks it at all
#: has an RMSE far below this after the transient (measured: ≈ 0.04 rad/s at 500 Hz, 6 s).
OMEGA_RMSE_BOUND = 0.2
#: η never exceeds (α0 + α1)/σ0 ≈ 1.3e-3 rad; a tracking estimate stays well below it.
ETA_RMSE_BOUND = 5e-4


# ------------------------------------------------------------------ stubs with known outcomes
def _fake_data(seed: int) -> SimpleNamespace:
    """Constant plant: x ≡ (1, 2), θ = 0.5, y = seed (the stub observer reads the seed)."""
    t = np.linspace(0.0, 1.0, 11)
    return SimpleNamespace(t=t, u=np.zeros((11, 1)), y=np.full((11, 1), float(seed)),
                           x=np.tile([1.0, 2.0], (11, 1)), theta=np.array([0.5]))


class _StubObserver:
    """Perfect estimates, except: ``huge`` seeds give x̂ = 1e9, ``raises`` seeds raise."""

    def __init__(self, huge=(), raises=()):
        self.huge, self.raises = set(huge), set(raises)

    def init(self, theta_hat0):
        return np.asarray(theta_hat0, dtype=float)

    def run(self, t, u, y, state0, throw=True):
        seed = int(y[0, 0])
        if seed in self.raises:
            raise NonFiniteError("the observer state became non-finite")
        x_hat = np.tile([1.0, 2.0], (t.size, 1)) * (1e9 if seed in self.huge else 1.0)
        theta_hat = np.full((t.size, 1), 0.5)
        return SimpleNamespace(t=t, x_hat=x_hat, theta_hat=theta_hat, phi_hat=None,
                               x_hat_refined=x_hat.copy())


def _stub_factory(outcomes):
    return lambda eps: _StubObserver(**outcomes.get(eps, {}))


def test_divergence_is_recorded_per_run_and_summarised():
    outcomes = {0.5: {"huge": [1]}, 0.3: {"raises": [0, 1]}}
    res = eps_sweep(_stub_factory(outcomes), _fake_data, [1.0, 0.5, 0.3], seeds=[0, 1],
                    theta_hat0=[0.5], progress=False)
    assert isinstance(res, SweepResult)
    np.testing.assert_array_equal(res.diverged, [[False, False], [False, True], [True, True]])
    np.testing.assert_allclose(res.fraction_stable, [1.0, 0.5, 0.0])
    assert res.stable_down_to == 1.0
    assert res.first_unstable == 0.5
    assert res.errors[2][0].startswith("NonFiniteError") and res.errors[1][0] is None
    # a divergence that raised nothing is reported too, naming the estimate that left its scale
    assert res.errors[1][1].startswith("x_hat[0] reached 1e+09"), res.errors[1][1]
    # perfect runs: settled at t[0], zero errors; failed runs: NaN
    assert res.t_1pct[0, 0] == 0.0 and res.x_rmse[0, 0].tolist() == [0.0, 0.0]
    assert np.all(np.isnan(res.x_rmse[2]))
    rows = res.rows
    assert [r.n_stable for r in rows] == [2, 1, 0]
    assert rows[1].x_rmse_median.tolist() == [0.0, 0.0]      # the diverged run is left out
    assert math.isnan(rows[2].theta_rmse_median)
    text = res.table(["omega", "eta"])
    assert "0/2" in text and "omega RMSE" in text
    assert "down to ε = 1" in text and "from ε = 0.5" in text
    json.dumps(res.to_dict(), allow_nan=False)               # NaN and inf became null


def test_non_monotone_outcome_is_reported_as_such():
    res = eps_sweep(_stub_factory({0.5: {"raises": [0]}}), _fake_data, [1.0, 0.5, 0.2],
                    seeds=[0], theta_hat0=[0.5], progress=False)
    assert res.stable_down_to == 0.2 and res.first_unstable == 0.5
    assert "not monotone" in res.verdict()


@pytest.mark.parametrize("eps, match", [
    ([0.5, 0.3], "start at 1"),
    ([1.0, 0.5, 0.7], "decrease strictly"),
    ([1.0, 1.0], "decrease strictly"),
    ([1.0, 0.0], r"\(0, 1\]"),
    ([], "no value"),
])
def test_eps_values_must_start_at_one_and_decrease(eps, match):
    with pytest.raises(DesignError, match=match):
        eps_sweep(_stub_factory({}), _fake_data, eps, seeds=[0], theta_hat0=[0.5],
                  progress=False)


@pytest.mark.parametrize("seeds", [[], [-1], [0.5]])
def test_bad_seeds_raise(seeds):
    with pytest.raises(DimensionError, match="seeds"):
        eps_sweep(_stub_factory({}), _fake_data, [1.0], seeds=seeds, theta_hat0=[0.5],
                  progress=False)


def test_setup_errors_are_not_mistaken_for_divergence():
    def broken(eps):
        raise DesignError("chain poles must lie in the open left half-plane")
    with pytest.raises(DesignError, match="chain poles"):
        eps_sweep(broken, _fake_data, [1.0], seeds=[0], theta_hat0=[0.5], progress=False)


# ------------------------------------------------------------------ the paper's example
@pytest.fixture(scope="module")
def lugre_sweep() -> SweepResult:
    sim = functools.partial(lugre.simulate, t_end=6.0, fs=500.0)
    return eps_sweep(lugre.observer, sim, [1.0, 0.5], seeds=[0, 1], theta_hat0=[0.5],
                     progress=False)


def test_lugre_sweep_is_stable_and_accurate(lugre_sweep):
    res = lugre_sweep
    assert res.diverged.shape == (2, 2) and not res.diverged.any()
    assert res.stable_down_to == 0.5 and res.first_unstable is None
    assert res.x_rmse.shape == res.x_rmse_refined.shape == (2, 2, 2)
    assert np.all(res.x_rmse[..., 0] < OMEGA_RMSE_BOUND)
    assert np.all(res.x_rmse_refined[..., 1] < ETA_RMSE_BOUND)
    # θ̂ is projected onto Θ = [0.05, 1]: its error can never exceed the distance to α0
    assert np.all(res.theta_max_error <= max(0.28 - 0.05, 1.0 - 0.28))
    text = res.table(["omega", "eta"])
    assert text.count("2/2") == 2 and "no divergence" in text
    assert json.loads(json.dumps(res.to_dict()))["stable_down_to"] == 0.5


def test_lugre_sweep_runs_match_a_single_run(lugre_sweep):
    """A sweep entry is the metric of the same run done by hand (seed 1, ε = 0.5)."""
    data = lugre.simulate(seed=1, t_end=6.0, fs=500.0)
    obs = lugre.observer(0.5)
    res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=[0.5]))
    half = int(np.searchsorted(data.t, 3.0))
    err = np.abs(res.theta_hat[half:, 0] - 0.28)
    assert lugre_sweep.theta_max_error[1, 1] == pytest.approx(float(err.max()), rel=1e-12)
