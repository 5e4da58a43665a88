"""Shared fixtures: a seeded Generator, the paper's DC motor, random left-invertible systems."""

from __future__ import annotations

import os

# One BLAS thread per process, set before NumPy loads OpenBLAS: the suite's matrices are tiny,
# and on a shared 2-core machine OpenBLAS's spinning threads made a 3×3 expm 10 ms instead of
# 12 µs (the two-inertia tests took 4 min instead of 25 s). Users' own settings win.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import importlib.util  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from thetahat.testing import STRUCTURES, random_scb_system  # noqa: E402


#: Without the speed extra the printed kernels of the EKF, the MAP fits, the likelihood and the
#: trust report run as plain Python, about a thousand times slower: a test marked
#: ``needs_speed`` (a real record's trust report, fits of thousands of samples, …) would take
#: minutes there. ``make test-core`` (no extra at all) skips those and runs the rest, which
#: cover the same Python paths on shorter records.
HAVE_NUMBA = importlib.util.find_spec("numba") is not None


def pytest_collection_modifyitems(config, items):
    if HAVE_NUMBA:
        return
    skip = pytest.mark.skip(reason="needs the speed extra (numba): its records take minutes "
                                   "in plain Python (tests/conftest.py, needs_speed)")
    for item in items:
        if item.get_closest_marker("needs_speed") is not None:
            item.add_marker(skip)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20260101)


@dataclass(frozen=True)
class DCMotor:
    """Sec. VIII: J ω̇ = u − F, LuGre friction; x = (ω, η), y = ω."""

    J: float = 0.0023
    sigma0: float = 260.0
    sigma1: float = 0.6
    alpha0: float = 0.28
    alpha1: float = 0.05
    alpha2: float = 0.176
    omega0: float = 0.01

    def linear(self, sigma1: float | None = None):
        s1 = self.sigma1 if sigma1 is None else sigma1
        A = np.array([[-(self.alpha2 + s1) / self.J, -self.sigma0 / self.J], [1.0, 0.0]])
        B = np.array([[1.0 / self.J], [0.0]])
        E = np.array([[s1 / self.J], [-1.0]])
        C = np.array([[1.0, 0.0]])
        return A, B, E, C

    def extended(self, sigma1: float | None = None):
        """The error system (4) with K = 0: (A_e, E_e, C_e) written out as in Sec. VIII-A."""
        s1 = self.sigma1 if sigma1 is None else sigma1
        J, s0, a2 = self.J, self.sigma0, self.alpha2
        A_e = np.array([[-(a2 + s1) / J, -s0 / J, s1 / J], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
        return A_e, np.array([[0.0], [0.0], [1.0]]), np.array([[1.0, 0.0, 0.0]])


@pytest.fixture(scope="session")
def dc_motor() -> DCMotor:
    return DCMotor()




@pytest.fixture(params=sorted(STRUCTURES))
def known_system(request):
    lengths, n_a, n_b, r_b = STRUCTURES[request.param]
    seed = sorted(STRUCTURES).index(request.param)
    return random_scb_system(np.random.default_rng(seed), chain_lengths=lengths, n_a=n_a,
                             n_b=n_b, r_b=r_b)
