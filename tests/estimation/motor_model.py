"""The DC motor of Sec. VIII written out by hand for the observer tests.

Shared by test_observer.py and test_redesign.py; deliberately independent of
thetahat.models.lugre (and of SymbolicPerturbation), so the tests compare two derivations.
"""

from __future__ import annotations

import numpy as np

from thetahat.model.paramset import Box
from thetahat.model.perturbation import Perturbation

J, SIGMA0, SIGMA1, ALPHA0, ALPHA1, ALPHA2, OMEGA0 = 0.0023, 260.0, 0.6, 0.28, 0.05, 0.176, 0.01
A_MOTOR = np.array([[-(ALPHA2 + SIGMA1) / J, -SIGMA0 / J], [1.0, 0.0]])
B_MOTOR = np.array([[1.0 / J], [0.0]])
E_MOTOR = np.array([[SIGMA1 / J], [-1.0]])
C_MOTOR = np.array([[1.0, 0.0]])
THETA_SET = Box([0.05], [1.0])


class LuGreG(Perturbation):
    """g(v, x, θ) = σ0 η |y| / (θ + α1 exp(−(ω/ω0)²)), v = (u, y), x = (ω, η) (Remark 4)."""

    dims = (2, 1, 1, 1, 1)

    @staticmethod
    def _zeta(x: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        bump = ALPHA1 * np.exp(-(x[..., 0] / OMEGA0) ** 2)
        return th[..., 0] + bump, bump * (-2.0 * x[..., 0] / OMEGA0**2)

    @staticmethod
    def _batch(v: np.ndarray, x: np.ndarray, th: np.ndarray) -> tuple[int, ...]:
        return np.broadcast_shapes(v.shape[:-1], x.shape[:-1], th.shape[:-1])

    def g(self, v, x, th):
        zeta, _ = self._zeta(x, th)
        return (SIGMA0 * x[..., 1] * np.abs(v[..., 1]) / zeta)[..., None]

    def dg_dv(self, v, x, th):
        zeta, _ = self._zeta(x, th)
        out = np.zeros(self._batch(v, x, th) + (1, 2))
        out[..., 0, 1] = SIGMA0 * x[..., 1] * np.sign(v[..., 1]) / zeta
        return out

    def dg_dx(self, v, x, th):
        zeta, dzeta = self._zeta(x, th)
        out = np.zeros(self._batch(v, x, th) + (1, 2))
        out[..., 0, 0] = -SIGMA0 * x[..., 1] * np.abs(v[..., 1]) * dzeta / zeta**2
        out[..., 0, 1] = SIGMA0 * np.abs(v[..., 1]) / zeta
        return out

    def dg_dtheta(self, v, x, th):
        zeta, _ = self._zeta(x, th)
        return (-SIGMA0 * x[..., 1] * np.abs(v[..., 1]) / zeta**2)[..., None, None]


class ZeroG(Perturbation):
    """g ≡ 0 with the given dims (n, m, r, p, k)."""

    def __init__(self, dims: tuple[int, int, int, int, int]) -> None:
        self._dims = dims

    @property
    def dims(self):
        return self._dims

    def _z(self, v, x, th, tail):
        return np.zeros(np.broadcast_shapes(v.shape[:-1], x.shape[:-1], th.shape[:-1]) + tail)

    def g(self, v, x, th):
        return self._z(v, x, th, (self._dims[4],))

    def dg_dv(self, v, x, th):
        return self._z(v, x, th, (self._dims[4], self._dims[1] + self._dims[2]))

    def dg_dx(self, v, x, th):
        return self._z(v, x, th, (self._dims[4], self._dims[0]))

    def dg_dtheta(self, v, x, th):
        return self._z(v, x, th, (self._dims[4], self._dims[3]))
