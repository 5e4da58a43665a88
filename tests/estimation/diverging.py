"""Observers that diverge by construction, for the tests of a failed run's status.

The gains place the eigenvalues of L = [[A − K_x C, E], [−K_φ C, 0]], the linear part of the
observer's error dynamics, at GROWTH/dt · (1, 1.25, 1.5, …): with the exact exponential step
the linear part alone multiplies the state by e^GROWTH … per sample (≥ 0.26 decades), so the
state leaves DIVERGENCE_BOUND (1e100) a few hundred samples into a record, in a step where it
grows far too fast for rounding differences between back ends (≤ 1e-12 relative) to move the
crossing — unless g overflows first, at a step equally far from a knife-edge.
"""

from __future__ import annotations

import numpy as np
import scipy.signal

from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.observer.plan import linear_part

#: ln of the growth per sample of the slowest unstable mode (e^0.6 ≈ 1.8).
GROWTH = 0.6


def unstable_observer(obs: ModifiedHighGainObserver, dt: float) -> ModifiedHighGainObserver:
    """``obs`` (its system, law, second observer, NaN policy and hold) with gains that make it
    diverge at the sampling step ``dt``."""
    s = obs.system
    A, C, E = s.A, s.C, s.E
    n, k = E.shape
    A_ext = np.block([[A, E], [np.zeros((k, n + k))]])
    C_ext = np.hstack([C, np.zeros((C.shape[0], k))])
    poles = GROWTH / dt * (1.0 + 0.25 * np.arange(n + k))
    K = scipy.signal.place_poles(A_ext.T, C_ext.T, poles).gain_matrix.T
    eig = np.sort(np.linalg.eigvals(linear_part(A, C, E, K[:n], K[n:])).real)
    np.testing.assert_allclose(eig, poles, rtol=1e-6)            # the placement took
    return ModifiedHighGainObserver(system=s, K_x=K[:n], K_phi=K[n:],
                                    update_law=obs.update_law, second=obs.second,
                                    nan_policy=obs.nan_policy, hold=obs.hold)
