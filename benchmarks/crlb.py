"""Cramér–Rao lower bound for θ = α0 on the LuGre scenario (Sec. VIII): the benchmark's view.

Run:  .venv/bin/python benchmarks/crlb.py [--t-end 20] [--no-check]

The bound itself is the library's :func:`thetahat.crlb` (sensitivity equations of the model
with y = C x in g, i.e. the plant with its true |ω|, integrated by LSODA at rtol 1e-9; u linear
between the samples of the scenario's input): this module only adapts it to a
:class:`~thetahat.models.lugre.Scenario` and adds the benchmark's summary. With x(0) = (0, 0)
known, I(t) = Σ_{t_k ≤ t} (∂ω(t_k)/∂θ)² / σ² and CRLB(t) = 1/I(t); the bound with x(0)
unknown (θ block of the inverse 3×3 information over (θ, ω(0), η(0))) is reported alongside
and is practically the same, because the plant forgets x(0) within milliseconds. The
sensitivity is validated against central finite differences of ``lugre.simulate``
(noise-free) in θ, and the bound against the covariance P_θθ(t) of an EKF with the exact
model (tests/benchmarks and tests/estimation/test_crlb.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass

import numpy as np

import thetahat
from thetahat.models import lugre
from thetahat.models.lugre import Scenario

__all__ = ["CRLBResult", "output_sensitivity", "crlb", "finite_difference_check"]

#: Relative step of the central finite difference in θ. ω(t; θ) is strongly curved in θ near
#: velocity reversals (the reversal time moves with θ), so the O(δθ²) truncation error
#: dominates: measured on 4 s, max |S − S_fd| = 0.83, 4.5e-3, 1.4e-4 for steps 1e-2, 1e-3,
#: 1e-4 (÷ 100 per ÷ 10, as O(δθ²) predicts); at 1e-4 the simulation's ~3e-8 rad/s error
#: divided by 2δθ = 5.6e-5 (≤ 5e-4) is the floor.
FD_REL_STEP = 1e-4


@dataclass(frozen=True, slots=True, eq=False)
class CRLBResult:
    """The bound for one scenario.

    Attributes
    ----------
    t : ndarray (N,)
        Sample times.
    sensitivity : ndarray (N,)
        ∂ω(t_k)/∂θ (rad/s per N m).
    var_t : ndarray (N,)
        CRLB(t_k) on var(θ̂) using samples 0..k (inf while I = 0).
    var : float
        CRLB with all N samples (x(0) known).
    var_x0_unknown : float
        The same with x(0) = (ω(0), η(0)) estimated as well.
    noise_std, theta : float
    """

    t: np.ndarray
    sensitivity: np.ndarray
    var_t: np.ndarray
    var: float
    var_x0_unknown: float
    noise_std: float
    theta: float

    @property
    def std(self) -> float:
        return float(np.sqrt(self.var))

    def std_at(self, t: float) -> float:
        """√CRLB using the samples up to time t."""
        k = int(np.searchsorted(self.t, t, side="right")) - 1
        return float(np.sqrt(self.var_t[max(k, 0)]))

    def time_to(self, rel: float, n_sigma: float = 3.0) -> float:
        """First t with n_sigma·√CRLB(t) ≤ rel·θ: an efficient estimator's ±n_sigma band fits
        inside ±rel·θ from then on (√CRLB(t) is non-increasing)."""
        ok = n_sigma * np.sqrt(self.var_t) <= rel * self.theta
        return float(self.t[int(np.argmax(ok))]) if ok.any() else float("inf")

    def summary(self) -> dict:
        """JSON-ready summary (the ``crlb`` block of out/bench.json)."""
        grid = [t for t in (0.5, 1, 2, 5, 10, 15, 20) if t <= self.t[-1] + 1e-9]
        return dict(theta=self.theta, noise_std=self.noise_std, t_end=float(self.t[-1]),
                    var=self.var, std=self.std, rel_std=self.std / self.theta,
                    std_x0_unknown=float(np.sqrt(self.var_x0_unknown)),
                    std_at={f"{t:g}": self.std_at(t) for t in grid},
                    t_5pct_3sigma=self.time_to(0.05), t_1pct_3sigma=self.time_to(0.01))


def _scenario(scenario: Scenario | None, overrides: dict) -> Scenario:
    sc = Scenario() if scenario is None else scenario
    return dataclasses.replace(sc, **overrides) if overrides else sc


def _bound(sc: Scenario, x0_known: bool) -> thetahat.CRLBResult:
    traj = lugre.simulate(0, scenario=sc, noise_std=0.0)
    return thetahat.crlb(lugre.system(sc.params), traj.t, traj.u, theta=[sc.theta],
                         noise_std=max(sc.noise_std, 1e-300), x0=sc.x0, x0_known=x0_known)


def output_sensitivity(scenario: Scenario | None = None, **overrides):
    """(t, x, ∂ω/∂θ) on the scenario's sampling grid (from :func:`thetahat.crlb`)."""
    sc = _scenario(scenario, overrides)
    b = _bound(sc, True)
    return b.t, b.x, b.sensitivity[:, 0, 0]


def crlb(scenario: Scenario | None = None, **overrides) -> CRLBResult:
    """The CRLB on θ for the scenario, for the whole record and as a function of time."""
    sc = _scenario(scenario, overrides)
    if sc.noise_std <= 0:
        raise ValueError("the CRLB needs noise_std > 0.")
    known = _bound(sc, True)
    unknown = _bound(sc, False)
    var_t = known.cov[:, 0, 0]
    return CRLBResult(t=known.t, sensitivity=known.sensitivity[:, 0, 0], var_t=var_t,
                      var=float(var_t[-1]), var_x0_unknown=float(unknown.cov[-1, 0, 0]),
                      noise_std=sc.noise_std, theta=sc.theta)


def sensitivity_pair(scenario: Scenario | None = None, rel_step: float = FD_REL_STEP,
                     **overrides) -> tuple[np.ndarray, np.ndarray]:
    """(S, S_fd): S = ∂ω/∂θ on the sampling grid from :func:`thetahat.crlb`, S_fd the central
    differences of ``lugre.simulate`` (noise-free, LSODA) at θ ± rel_step·θ."""
    sc = _scenario(scenario, overrides)
    d = rel_step * sc.theta

    def omega(theta):
        p = dataclasses.replace(sc.params, alpha0=theta)
        return lugre.simulate(0, scenario=sc, noise_std=0.0, params=p).y_clean[:, 0]

    s_fd = (omega(sc.theta + d) - omega(sc.theta - d)) / (2 * d)
    _, _, S = output_sensitivity(sc)
    return S, s_fd


def finite_difference_check(scenario: Scenario | None = None, rel_step: float = FD_REL_STEP,
                            **overrides) -> tuple[float, float]:
    """(max |S − S_fd|, max |S|) of :func:`sensitivity_pair`."""
    S, s_fd = sensitivity_pair(scenario, rel_step, **overrides)
    return float(np.max(np.abs(S - s_fd))), float(np.max(np.abs(S)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=20.0)
    ap.add_argument("--no-check", action="store_true", help="skip the finite-difference check")
    args = ap.parse_args()
    sc = Scenario(t_end=args.t_end)
    t0 = time.perf_counter()
    res = crlb(sc)
    wall = time.perf_counter() - t0
    print(f"CRLB for θ = α0 = {sc.theta} N m, σ = {sc.noise_std} rad/s, fs = {sc.fs:g} Hz, "
          f"{sc.t_end:g} s  ({wall:.1f} s)")
    print(f"  √CRLB (all data)      = {res.std:.3e} N m  ({100 * res.std / sc.theta:.4f} % of θ)")
    print(f"  √CRLB, x(0) unknown   = {np.sqrt(res.var_x0_unknown):.3e} N m")
    for t in (0.1, 0.5, 1, 2, 5, 10, 15, 20):
        if t <= sc.t_end:
            print(f"  √CRLB(t ≤ {t:>4g} s)    = {res.std_at(t):.3e} N m")
    print(f"  3√CRLB(t) ≤ 5 % θ from t = {res.time_to(0.05):.3f} s; ≤ 1 % θ from "
          f"t = {res.time_to(0.01):.3f} s")
    if not args.no_check:
        err, scale = finite_difference_check(sc)
        print(f"  sensitivity vs central differences of lugre.simulate: max |Δ| = {err:.2e} "
              f"(max |∂ω/∂θ| = {scale:.3g}, relative {err / scale:.1e})")


if __name__ == "__main__":
    main()
