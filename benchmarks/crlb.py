"""Cramér–Rao lower bound for θ = α0 on the LuGre scenario (Sec. VIII), by sensitivity equations.

Run:  .venv/bin/python benchmarks/crlb.py [--t-end 20] [--no-check]

With y_k = ω(t_k; θ) + e_k, e_k ~ N(0, σ²) white, the Fisher information about θ in the data
up to t is I(t) = Σ_{t_k ≤ t} (∂ω(t_k)/∂θ)² / σ², and any unbiased estimator of θ from those
data has variance ≥ CRLB(t) = 1 / I(t). The output sensitivity S = ∂x/∂θ, x = (ω, η), solves
the sensitivity equations integrated alongside the plant ẋ = A x + B u + E φ(x, θ) (true |ω|):

    Ṡ = (A + E ∂φ/∂x) S + E ∂φ/∂θ,   S(0) = 0,   ∂φ/∂θ = −σ0 η |ω| / ζ(ω, θ)².

x(0) = (0, 0) is known in the scenario; the bound with x(0) unknown (a 3×3 Fisher matrix over
(θ, ω(0), η(0)), with M = ∂x/∂x(0), Ṁ = (A + E ∂φ/∂x) M, M(0) = I) is reported alongside and
is practically the same, because the plant forgets x(0) within milliseconds. The sensitivity
is validated against central finite differences of ``lugre.simulate`` (noise-free) in θ, and
the bound against the covariance P_θθ(t) of an EKF with the exact model, no process noise and
θ at its true value (equal to 0.3 % at 2 s and 0.03 % at 20 s; tests/benchmarks).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from thetahat.models import lugre
from thetahat.models.lugre import Scenario

__all__ = ["CRLBResult", "output_sensitivity", "crlb", "finite_difference_check"]

#: Integrator settings of the sensitivity solve: the plant's own (LSODA, rtol 1e-9), with the
#: absolute tolerances of (ω, η) from lugre and the same ratio for the sensitivities.
RTOL = lugre.LUGRE_RTOL
ATOL = np.array([1e-10, 1e-13, 1e-10, 1e-13, 1e-10, 1e-13, 1e-10, 1e-13])
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


def _rhs_factory(sc: Scenario):
    p = sc.params
    J, s0, s1, a1, a2, w0 = p.J, p.sigma0, p.sigma1, p.alpha1, p.alpha2, p.omega0
    th = sc.theta
    A = np.array([[-(a2 + s1) / J, -s0 / J], [1.0, 0.0]])
    E = np.array([s1 / J, -1.0])
    amp = np.asarray(sc.u.amplitudes, float)[0]
    frq = 2.0 * np.pi * np.asarray(sc.u.frequencies, float)[0]
    ph = np.asarray(sc.u.phases, float)[0]
    off = float(np.asarray(sc.u.offset, float)[0])

    def pieces(x):
        w, eta = x[0], x[1]
        strb = a1 * np.exp(-(w / w0) ** 2)
        zeta = th + strb
        dzeta = -2.0 * w / w0 ** 2 * strb
        aw = abs(w)
        phi = s0 * eta * aw / zeta
        phi_x = np.array([s0 * eta * (np.sign(w) * zeta - aw * dzeta) / zeta ** 2, s0 * aw / zeta])
        phi_t = -s0 * eta * aw / zeta ** 2
        return phi, phi_x, phi_t

    def rhs(t, s):
        x = s[:2]
        phi, phi_x, phi_t = pieces(x)
        u = off + float(np.dot(amp, np.sin(frq * t + ph)))
        Jx = A + np.outer(E, phi_x)
        dx = A @ x + np.array([u / J, 0.0]) + E * phi
        dS = Jx @ s[2:4] + E * phi_t
        dM = Jx @ s[4:8].reshape(2, 2)
        return np.concatenate([dx, dS, dM.ravel()])

    def jac(t, s):
        # block lower-triangular with the second-derivative couplings left out: LSODA uses
        # the Jacobian only in its Newton iteration, so an approximation costs iterations only
        _, phi_x, _ = pieces(s[:2])
        Jx = A + np.outer(E, phi_x)
        out = np.zeros((8, 8))
        for i in range(4):
            out[2 * i:2 * i + 2, 2 * i:2 * i + 2] = Jx
        return out

    return rhs, jac


def output_sensitivity(scenario: Scenario | None = None, **overrides):
    """(t, x, ∂x/∂θ, ∂x/∂x(0)) on the scenario's sampling grid, from the sensitivity equations.

    Only multisine inputs (the scenario's default kind) are supported.
    """
    sc = Scenario() if scenario is None else scenario
    if overrides:
        sc = dataclasses.replace(sc, **overrides)
    rhs, jac = _rhs_factory(sc)
    n = int(round(sc.t_end * sc.fs)) + 1
    t = np.arange(n) / sc.fs
    s0 = np.concatenate([np.asarray(sc.x0, float), [0.0, 0.0], np.eye(2).ravel()])
    sol = solve_ivp(rhs, (0.0, t[-1]), s0, method="LSODA", t_eval=t, jac=jac, rtol=RTOL,
                    atol=ATOL)
    if not sol.success:
        raise RuntimeError(f"sensitivity integration failed: {sol.message}")
    Y = sol.y.T
    return t, Y[:, :2], Y[:, 2:4], Y[:, 4:8].reshape(-1, 2, 2)


def crlb(scenario: Scenario | None = None, **overrides) -> CRLBResult:
    """The CRLB on θ for the scenario, for the whole record and as a function of time."""
    sc = Scenario() if scenario is None else scenario
    if overrides:
        sc = dataclasses.replace(sc, **overrides)
    if sc.noise_std <= 0:
        raise ValueError("the CRLB needs noise_std > 0.")
    t, _, S, M = output_sensitivity(sc)
    s_w = S[:, 0]
    info_t = np.cumsum(s_w ** 2) / sc.noise_std ** 2
    with np.errstate(divide="ignore"):
        var_t = np.where(info_t > 0, 1.0 / np.where(info_t > 0, info_t, 1.0), np.inf)
    g = np.column_stack([s_w, M[:, 0, 0], M[:, 0, 1]])          # ∂y/∂(θ, ω(0), η(0))
    fim = g.T @ g / sc.noise_std ** 2
    var_x0 = float(np.linalg.inv(fim)[0, 0])
    return CRLBResult(t=t, sensitivity=s_w, var_t=var_t, var=float(var_t[-1]),
                      var_x0_unknown=var_x0, noise_std=sc.noise_std, theta=sc.theta)


def finite_difference_check(scenario: Scenario | None = None, rel_step: float = FD_REL_STEP,
                            **overrides) -> tuple[float, float]:
    """(max |S − S_fd|, max |S|): S = ∂ω/∂θ from the sensitivity equations against central
    differences of ``lugre.simulate`` (noise-free) at θ ± rel_step·θ."""
    sc = Scenario() if scenario is None else scenario
    if overrides:
        sc = dataclasses.replace(sc, **overrides)
    d = rel_step * sc.theta

    def omega(theta):
        p = dataclasses.replace(sc.params, alpha0=theta)
        return lugre.simulate(0, scenario=sc, noise_std=0.0, params=p).y_clean[:, 0]

    s_fd = (omega(sc.theta + d) - omega(sc.theta - d)) / (2 * d)
    _, _, S, _ = output_sensitivity(sc)
    return float(np.max(np.abs(S[:, 0] - s_fd))), float(np.max(np.abs(S[:, 0])))


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
