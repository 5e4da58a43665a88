"""The model run free over an input record: the validation simulation, under a stated hold.

:func:`simulate_output` runs the plant model of eq. (1) (y = C x substituted into g) from x(t₀)
at a given θ over a sampled input record, with u between the samples as the hold reconstructs
it (:mod:`~thetahat.estimation.hold`: ``"zoh"``, ``"foh"`` or ``"bandlimited"``), by the
sampled-data map every estimator of stage 2 uses
(:mod:`~thetahat.estimation.statistical.plant_kernel`: RK4 with the sub-steps of a sample the
larger of the stability choice and an accuracy floor). The floor is chosen by step doubling
(:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`) so that the simulated
output's RMS error is at most ``tolerance``: the same rule, at the same accuracy, by which the
estimators choose theirs (there ``tolerance`` is a tenth of a standard error of θ̂ spread over
the record, σ / (10 √N)). A model fitted by thetahat is validated with the simulation it was
fitted with: the same hold, the same accuracy.

The ``"foh"`` hold reconstructs u from stage 2's samples ũ
(:func:`~thetahat.estimation.statistical.input_hold.stage2_samples`: a sampled smooth input
corrected so that each interval carries its mean), as the estimators do.

What it may import: the model, the record checks, the hold and, in this room, ``input_hold``
and ``plant_kernel``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_vector
from ...errors import DimensionError, SimulationError
from ...model.system import PerturbedLinearSystem
from ..hold import check_hold
from ..records import check_record
from .input_hold import stage2_samples
from .plant_kernel import H_RHO, Propagation, choose_substeps, model_kernel

__all__ = ["SimulatedOutput", "simulate_output", "DEFAULT_RTOL"]

FloatArray = NDArray[np.float64]

#: The default tolerance of :func:`simulate_output`, relative to the output's RMS value.
DEFAULT_RTOL = 1e-6


@dataclass(frozen=True, slots=True, eq=False)
class SimulatedOutput:
    """A free run of the model (:func:`simulate_output`).

    Attributes
    ----------
    t : ndarray, shape (N,)
    y : ndarray, shape (N, r)
        C x(t_k).
    x : ndarray, shape (N, n)
    hold : str
    substeps : int
        The RK4 sub-steps' accuracy floor used (the stability choice may take more).
    tolerance : ndarray, shape (r,)
        The RMS output error the sub-steps were chosen for.
    """

    t: FloatArray
    y: FloatArray
    x: FloatArray
    hold: str
    substeps: int
    tolerance: FloatArray

    def rms_error(self, y: ArrayLike) -> FloatArray:
        """RMS of the measured minus the simulated output per output channel (NaN skipped).

        Parameters
        ----------
        y : array_like, shape (N, r)

        Returns
        -------
        ndarray, shape (r,)
        """
        Y = np.asarray(y, dtype=np.float64).reshape(self.y.shape)
        e = Y - self.y
        return np.sqrt(np.nanmean(e * e, axis=0))

    def __repr__(self) -> str:
        return (f"SimulatedOutput(N={self.t.shape[0]}, hold={self.hold!r}, "
                f"substeps={self.substeps})")


def simulate_output(system: PerturbedLinearSystem, theta: ArrayLike, t: ArrayLike,
                    u: ArrayLike | None, *, x0: ArrayLike | None = None, hold: str = "foh",
                    tolerance: ArrayLike | None = None, substeps: int | None = None,
                    h_rho: float = H_RHO, compiled: bool | None = None) -> SimulatedOutput:
    """The model's output run free from x0 at θ over an input record, under a stated hold.

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a symbolic g (:func:`~thetahat.estimation.statistical.plant_kernel.model_kernel`).
    theta : array_like, shape (p,)
    t : array_like, shape (N,)
        Strictly increasing sampling instants (N ≥ 2).
    u : array_like, shape (N, m) or (N,), or None when m = 0
        The input samples.
    x0 : array_like, shape (n,), optional
        x(t₀) (default zeros).
    hold : {"zoh", "foh", "bandlimited"}
        u between the samples (module docstring).
    tolerance : float or array_like (r,), optional
        The RMS output error allowed, per output; default :data:`DEFAULT_RTOL` times the RMS
        of the output simulated with the stability sub-steps alone.
    substeps : int, optional
        The sub-steps' floor itself (then ``tolerance`` is not used).
    h_rho : float
        The stability bound per sub-step (:data:`~.plant_kernel.H_RHO`).
    compiled : bool, optional
        numba kernels (default: when installed).

    Returns
    -------
    SimulatedOutput

    Raises
    ------
    DimensionError
        Wrong shapes, or a tolerance that is not positive.
    SimulationError
        The trajectory stops being finite (the message names the sample).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.free_run import simulate_output
    >>> d = lugre.simulate(seed=0, t_end=0.3)
    >>> sim = simulate_output(lugre.system(), [0.28], d.t, d.u, compiled=False)
    >>> bool(np.all(sim.rms_error(d.y) < 1.5 * 0.02))      # the noise (σ = 0.02) is what is left
    True
    """
    n, m, r, p = system.n, system.m, system.r, system.p
    t_, U, _ = check_record(t, u, np.zeros((np.size(t), r)), m=m, r=r)
    th = as_vector("theta", theta, p)
    x0_ = np.zeros(n) if x0 is None else as_vector("x0", x0, n)
    kern = model_kernel(system, compiled=compiled)
    Us = stage2_samples(U, check_hold(hold))[0]
    N = t_.shape[0]
    Y, X = np.full((N, r), np.nan), np.full((N, n), np.nan)

    def run(floor: int) -> int:
        pc, WT = Propagation(hold=hold, substeps=floor, h_rho=h_rho).arrays()
        return int(kern.free_run(x0_.copy(), th, Us, t_, 0, N, pc, WT, Y, X))

    if substeps is None:
        if tolerance is None:
            run(1)
            rms = np.sqrt(np.nanmean(Y * Y, axis=0)) if np.isfinite(Y).any() else np.ones(r)
            tol = DEFAULT_RTOL * np.where(np.isfinite(rms) & (rms > 0), rms, 1.0)
        else:
            tol = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (r,)).copy()
        if not np.all(np.isfinite(tol) & (tol > 0)):
            raise DimensionError(f"tolerance must be positive and finite; got {tol}.")
        # choose_substeps' criterion with σ = tolerance √N: the RMS error at most tolerance
        substeps = choose_substeps(kern, t_, Us, np.full((N, r), np.nan), th, x0_,
                                   tol * np.sqrt(N), hold=hold, h_rho=h_rho, target=1.0)
    else:
        tol = np.full(r, np.nan)
    done = run(int(substeps))
    if done < N:
        raise SimulationError(f"the model's trajectory stops being finite at t[{done}] = "
                              f"{float(t_[done]):.6g}: check θ, x0 and the input's scale.")
    return SimulatedOutput(t=t_, y=Y, x=X, hold=hold, substeps=int(substeps), tolerance=tol)
