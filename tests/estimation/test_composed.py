"""Issue acceptance: each proposition's law composed with the modified high-gain observer.

For each worked example (Props. 1–4) the gains are designed by ``modified_high_gain`` on the
example's linear part, the plant is simulated with the true θ, and the observer starts from
the corners of Θ. Noise-free: θ̂ → θ to 1e-3 relative; with measurement noise: θ̂ stays in Θ
and its error stays bounded (the bound is reported in the assertion message).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from thetahat import (ModifiedHighGainObserver, WhiteNoise, modified_high_gain,
                      simulate_plant)
from thetahat.models import prop1_sinh, prop2_tanh, prop3_monotone, prop4_pe

#: Noise-free convergence target of the issue.
NOISE_FREE_RTOL = 1e-3
#: With noise σ = 0.01 on y, the final error must stay within this fraction of Θ's width.
NOISY_BOUND = 0.1
#: (module, ε, horizon [s]): ε = 0.2 and horizons about 1.5× the measured time to 1e-3
#: (prop1 4.5 s, prop2 18 s, prop3 2 s, prop4 12 s from the worst corner).
CASES = [(prop1_sinh, 0.2, 8.0), (prop2_tanh, 0.2, 28.0), (prop3_monotone, 0.2, 5.0),
         (prop4_pe, 0.2, 20.0)]
#: With noise a smaller ε amplifies it (Sec. VII): on Prop. 2 the last-quarter θ̂ RMSE is
#: 40 % of θ at ε = 0.2, 6 % at ε = 0.5 and 25 % at ε = 1 (slower) — measured, seed 1.
NOISY_EPS = {"prop2_tanh": 0.5}
FS = 200.0
#: First-order hold of the samples: with ZOH the half-sample delay at 200 Hz leaves a
#: measured 4e-3 relative bias in θ̂ on the Prop. 2 example (FOH: 1e-8).
HOLD = "foh"


def _corners(box):
    return [np.array(c) for c in itertools.product(*zip(box.lower, box.upper))]


def _data(mod, t_end, noise, seed=0):
    sys = mod.system()
    g = sys.perturbation

    def phi(t, x, u, theta):
        x = np.asarray(x, float)
        u = np.asarray(u, float)
        v = np.concatenate([u, x @ sys.C.T], axis=-1)
        return g.g(v, x, np.broadcast_to(theta, x.shape[:-1] + (len(theta),)))

    return sys, simulate_plant(sys, phi=phi, u=lambda t: mod.input_signal(t), t_end=t_end,
                               fs=FS, x0=np.zeros(sys.n), theta=mod.THETA,
                               noise=None if noise == 0 else WhiteNoise(noise), seed=seed,
                               rtol=1e-9, atol=1e-11)


def _observer(mod, sys, eps):
    d = modified_high_gain(sys.A, sys.E, sys.C, eps)
    return ModifiedHighGainObserver.from_design(sys, d, mod.update_law(), hold=HOLD)


@pytest.mark.parametrize("mod, eps, t_end", CASES, ids=lambda v: getattr(v, "__name__", str(v)))
def test_noise_free_convergence_from_the_corners(mod, eps, t_end):
    sys, data = _data(mod, t_end, noise=0.0)
    obs = _observer(mod, sys, eps)
    box = mod.PARAMETER_SET
    for corner in _corners(box):
        res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=corner))
        assert np.all(box.contains(res.theta_hat)), "θ̂ left Θ"
        err = np.abs(res.theta_hat[-1] - mod.THETA) / np.abs(mod.THETA)
        assert np.all(err <= NOISE_FREE_RTOL), (mod.__name__, corner, res.theta_hat[-1])


@pytest.mark.parametrize("mod, eps, t_end", CASES, ids=lambda v: getattr(v, "__name__", str(v)))
def test_with_noise_bounded(mod, eps, t_end):
    sys, data = _data(mod, t_end, noise=0.01, seed=1)
    obs = _observer(mod, sys, NOISY_EPS.get(mod.__name__.rsplit(".", 1)[-1], eps))
    box = mod.PARAMETER_SET
    width = np.asarray(box.upper) - np.asarray(box.lower)
    res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=box.lower))
    assert np.all(box.contains(res.theta_hat))
    tail = 3 * data.t.size // 4          # the last quarter: after convergence from the corner
    worst = np.max(np.abs(res.theta_hat[tail:] - mod.THETA) / width)
    assert worst <= NOISY_BOUND, f"{mod.__name__}: worst error {worst:.3g} of Θ's width"
