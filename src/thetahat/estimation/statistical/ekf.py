"""The joint extended Kalman filter on col(x, θ) built from any thetahat model (stage 2 alone).

:class:`JointEKF` runs the kernels of :mod:`~thetahat.estimation.statistical.ekf_kernels` —
the sampled-data map of :mod:`~thetahat.estimation.statistical.plant_kernel` (RK4 sub-steps,
u between the samples as the ``hold`` reconstructs it) with θ constant:

    x_{k+1} = F_k(x_k, θ, u),   θ_{k+1} = θ_k,   y_k = C x_k + e_k,  e_k ~ N(0, R).

The hold is ``"smooth"`` unless told (:mod:`~thetahat.estimation.hold`): u linear between the
samples ũ of :func:`~thetahat.estimation.statistical.input_hold.smooth_input` (u_k where the
input is not resolved by its sampling; where it is, corrected so that the linear hold carries
u's exact mean over each interval to O(h⁴); causal, so ``step`` and ``run`` agree); ``"zoh"``
for an input held by a DAC; ``"foh"`` for one linear between its samples (the raw samples);
``"bandlimited"`` for a band-limited input (``run`` only). The RK4 sub-steps of a record are
chosen by :func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps` at the start
values unless given. Prediction P ← T P Tᵀ + Q (Q = diag(Q_x, 0), Q_x the process noise on x
over one sample), update in Joseph form, then θ projected onto Θ in the P_θθ⁻¹-weighted norm (a
box: a clip; any convex Θ, see :mod:`~thetahat.estimation.statistical.stage2_set`). R = σ² I
with σ given or estimated from the data
(:func:`~thetahat.estimation.statistical.noise_level.estimate_noise_std`); the prior on θ comes
from Θ (centre ± |Θ|/4 per component unless told), on x(0) it is wide
(:func:`~thetahat.estimation.statistical.common.joint_prior`).

A run whose state becomes non-finite stops there with
:attr:`~thetahat.estimation.status.Status.DIVERGED` (raised with ``throw=True``, returned with
``throw=False``); its message says when the innovations before show that the model taken as
exact does not fit the record (:func:`~thetahat.estimation.statistical.ekf_kernels.divergence_message`).

What it may import: :mod:`thetahat.model`, the package's helpers, the bottom of the estimation
wing (``protocol``, ``records``, ``status``), and, in this room, ``common``, ``ekf_kernels``,
``input_hold``, ``noise_level``, ``plant_kernel`` and ``stage2_set``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...model.system import PerturbedLinearSystem
from ..hold import DEFAULT_HOLD
from ..protocol import (Diagnostics, EstimateResult, check_state, missing_samples,
                        stream_sample)
from ..records import check_record
from ..status import Status
from .common import (RunStop, joint_prior, model_phi_hat, resolve_noise_std, stopped_result)
from .ekf_kernels import EKFKernels, divergence_message, ekf_kernels, ekf_sample
from .input_hold import InputHistory, stage2_samples, streamable
from .noise_level import MIN_SAMPLES
from .plant_kernel import H_RHO, Propagation, choose_substeps
from .stage2_set import stage2_set

__all__ = ["EKFDiagnostics", "EKFState", "JointEKF"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class EKFDiagnostics(Diagnostics):
    """What :meth:`JointEKF.run` reports beyond the common estimates (``result.diagnostics``).

    Attributes
    ----------
    theta_sd : ndarray, shape (N, p)
        √diag P_θθ after each update.
    nis : ndarray, shape (N,)
        Normalised innovation squared ÷ r (≈ 1 on average for a consistent filter; NaN where
        no update was made).
    noise_std : ndarray, shape (r,)
        σ used for R.
    substeps : int
        The RK4 sub-steps' accuracy floor the run propagated with.
    """

    theta_sd: FloatArray
    nis: FloatArray
    noise_std: FloatArray
    substeps: int = 1

    def __repr__(self) -> str:
        return (f"EKFDiagnostics(theta_sd[-1]={self.theta_sd[-1]}, "
                f"mean_nis={float(np.nanmean(self.nis)) if np.isfinite(self.nis).any() else None}, "
                f"noise_std={self.noise_std})")


@dataclass(frozen=True, slots=True, eq=False)
class EKFState:
    """The filter's state between two samples (from :meth:`JointEKF.init` or ``step``).

    Attributes
    ----------
    x_hat : ndarray, shape (n,)
    theta_hat : ndarray, shape (p,)
        The estimates after the last sample's update (θ̂ in Θ).
    P : ndarray, shape (n + p, n + p)
        Their covariance.
    k : int
        Samples processed.
    u_prev : ndarray, shape (m,)
        The last sample's input ũ (the next prediction holds u linear from it).
    u_history : InputHistory or None
        The raw inputs the next samples' ũ need
        (:func:`~thetahat.estimation.statistical.input_hold.smooth_input`).
    dt_prev : float
        Time from the last sample to the next one (the ``dt`` of the last ``step``).
    noise_std : ndarray, shape (r,), or None
        σ of R; None until known (then the first
        :data:`~thetahat.estimation.statistical.noise_level.MIN_SAMPLES` outputs are collected in
        ``y_first`` and no update is made before σ is estimated from them).
    y_first : ndarray, shape (j, r)
        Outputs collected while σ is unknown.
    nis : float
        The last update's normalised innovation squared ÷ r (NaN: no update).
    """

    x_hat: FloatArray
    theta_hat: FloatArray
    P: FloatArray
    k: int = 0
    u_prev: FloatArray | None = None
    dt_prev: float = 0.0
    u_history: InputHistory | None = None
    noise_std: FloatArray | None = None
    y_first: FloatArray | None = None
    nis: float = math.nan

    def __repr__(self) -> str:
        return (f"EKFState(k={self.k}, x_hat={self.x_hat}, theta_hat={self.theta_hat}, "
                f"noise_std={self.noise_std})")


@dataclass(frozen=True, slots=True, eq=False)
class JointEKF:
    """Extended Kalman filter on col(x, θ) for a thetahat model (stage 2 alone).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a symbolic g and any convex Θ (θ̂ is projected onto it after each update, see
        :mod:`~thetahat.estimation.statistical.stage2_set`).
    noise_std : float or array_like (r,), optional
        σ of the output noise; default: estimated from the record (:meth:`run`) or from the
        first samples (:meth:`step` delays its updates until :data:`MIN_SAMPLES` samples).
    theta_sd : array_like (p,), optional
        Prior standard deviation of θ; default |Θ|/4.
    x_sd : float or array_like (n,), optional
        Prior standard deviation of x(0); default
        :func:`~thetahat.estimation.statistical.common.x_prior_sd` of x̂(0) (wide: the data
        determine x quickly).
    q_x : float
        Process-noise variance per sample on x (default 0: the model is taken as exact).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`; default ``"smooth"``,
        ``"bandlimited"`` for :meth:`run` only).
    substeps : int, optional
        The RK4 sub-steps' accuracy floor; default: chosen per record at the start values
        (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`; 1 in
        :meth:`step`, which has no record).
    h_rho : float
        RK4 sub-step bound (see :mod:`~thetahat.estimation.statistical.plant_kernel`).
    compiled : bool, optional
        numba kernels (default: when installed).

    Notes
    -----
    An :class:`~thetahat.estimation.protocol.Estimator`: :meth:`init` gives an
    :class:`EKFState`, :meth:`step` processes one sample, :meth:`run` a record from a state;
    results carry :class:`EKFDiagnostics`. A prior covariance of one's own is a state of
    one's own: ``dataclasses.replace(ekf.init(theta_hat0=…), P=P0)``.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import JointEKF
    >>> data = lugre.simulate(seed=0, t_end=0.3)
    >>> ekf = JointEKF(system=lugre.system(), compiled=False)
    >>> res = ekf.run(data.t, data.u, data.y, state0=ekf.init(theta_hat0=[0.5]))
    >>> res.status.name, bool(abs(res.theta_hat[-1, 0] - 0.28) < 0.01)
    ('OK', True)
    """

    system: PerturbedLinearSystem
    noise_std: ArrayLike | None = None
    theta_sd: ArrayLike | None = None
    x_sd: ArrayLike | None = None
    q_x: float = 0.0
    hold: str = DEFAULT_HOLD
    substeps: int | None = None
    h_rho: float = H_RHO
    compiled: bool | None = None

    def __post_init__(self) -> None:
        Propagation(hold=self.hold, substeps=self.substeps or 1, h_rho=self.h_rho)

    @property
    def kernels(self) -> EKFKernels:
        """The per-sample kernels of this model (:func:`~.ekf_kernels.ekf_kernels`)."""
        return ekf_kernels(self.system, compiled=self.compiled)

    def prior(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None
              ) -> tuple[FloatArray, FloatArray]:
        """(s0, P0): x̂(0), θ̂(0) (default: zeros, centre of Θ) and the prior covariance.

        Parameters
        ----------
        x_hat0, theta_hat0 : array_like, optional
            The means (θ̂(0) in Θ).

        Returns
        -------
        s0 : ndarray (n + p,)
        P0 : ndarray (n + p, n + p)
            :func:`~thetahat.estimation.statistical.common.joint_prior` with this filter's
            ``theta_sd`` and ``x_sd``.
        """
        return joint_prior(self.system, x_hat0, theta_hat0, theta_sd=self.theta_sd,
                           x_sd=self.x_sd)

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None
             ) -> EKFState:
        """The filter's state before the first sample: x̂₀, θ̂₀ and the prior covariance.

        Parameters
        ----------
        x_hat0 : array_like (n,), optional
            Default zeros.
        theta_hat0 : array_like (p,), optional
            In Θ; default the centre of Θ.

        Returns
        -------
        EKFState

        Raises
        ------
        ParameterSetError
            θ̂₀ outside Θ.
        """
        n = self.system.n
        s, P = self.prior(x_hat0=x_hat0, theta_hat0=theta_hat0)
        sigma = (None if self.noise_std is None
                 else resolve_noise_std(self.noise_std, np.zeros((1, self.system.r))))
        return EKFState(x_hat=s[:n], theta_hat=s[n:], P=P, noise_std=sigma,
                        y_first=np.zeros((0, self.system.r)))

    def _check_state(self, state: Any) -> EKFState:
        """``state`` if it is an :class:`EKFState` of this model (:func:`check_state`)."""
        n, m, r, p = self.system.n, self.system.m, self.system.r, self.system.p
        return check_state("JointEKF", state, EKFState,
                           {"x_hat": (n,), "theta_hat": (p,), "P": (n + p, n + p),
                            "u_prev": (m,), "noise_std": (r,)})

    def step(self, state: EKFState, u: ArrayLike | None, y: ArrayLike, dt: float) -> EKFState:
        """Process the samples of one instant: predict from the previous one, then update.

        The state is a value: stepping one state twice gives the same next state twice (no
        stream is shared between states), and any JointEKF of the same model may step it.

        Parameters
        ----------
        state : EKFState
            From :meth:`init` or the previous ``step`` (not modified).
        u : array_like (m,)
            The input at this instant (``None`` when m = 0).
        y : array_like (r,)
            The output; NaN: no update (the filter predicts over it).
        dt : float
            Time to the next sample, > 0 (used by the next ``step``'s prediction).

        Returns
        -------
        EKFState
            The estimates at this instant (row k of :meth:`run` after k + 1 steps). Without a
            given ``noise_std`` no update is made before :data:`MIN_SAMPLES` outputs have
            come in (σ is then estimated from them); with one, a loop of ``step`` computes
            what :meth:`run` computes.

        Raises
        ------
        StateError
            Not an :class:`EKFState` of this model.
        DimensionError
            Wrong shapes or dt ≤ 0.
        NonFiniteError
            NaN or inf in u, inf in y, or the filter diverged.
        InputLimitError
            u, y or dt of a magnitude float64 arithmetic cannot take (rescale the unit).
        """
        sys_ = self.system
        n, r = sys_.n, sys_.r
        state = self._check_state(state)
        u_, y_, h = stream_sample(sys_, u, y, dt)
        s = np.concatenate([state.x_hat, state.theta_hat])
        P = np.array(state.P, dtype=np.float64, order="C")
        sigma, y_first = state.noise_std, state.y_first
        if sigma is None:
            y_first = np.vstack([np.zeros((0, r)) if y_first is None else y_first, y_[None]])
            if y_first.shape[0] >= MIN_SAMPLES:
                sigma = resolve_noise_std(None, y_first)
        u0 = (np.array(state.u_prev, dtype=np.float64)
              if state.k > 0 and state.u_prev is not None else None)
        ut, u_hist = stage2_samples(u_[None], streamable(self.hold, "JointEKF"),
                                    state.u_history)
        nis = ekf_sample(self.kernels, sys_, s, P, u0, ut[0], y_, state.dt_prev,
                         Propagation(hold=self.hold, substeps=self.substeps or 1,
                                     h_rho=self.h_rho),
                         self.q_x * np.eye(n), None if sigma is None else np.diag(sigma ** 2),
                         state.k)
        return EKFState(x_hat=s[:n], theta_hat=s[n:], P=P, k=state.k + 1, u_prev=ut[0],
                        dt_prev=h, u_history=u_hist, noise_std=sigma, y_first=y_first, nis=nis)

    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            state0: EKFState | None = None, throw: bool = True) -> EstimateResult:
        """Filter a record: sample 0 is an update at the prior (or, from a ``state0`` that has
        seen samples, a prediction from its last sample then an update), later samples
        predict then update.

        Parameters
        ----------
        t : array_like (N,)
        u : array_like (N, m) or (N,)
        y : array_like (N, r) or (N,); NaN samples are predicted over.
        state0 : EKFState, optional
            From :meth:`init` or :meth:`step` (default ``init()``). Its σ is used when
            known; else σ is estimated from the record.
        throw : bool
            What a divergence does (:mod:`~thetahat.estimation.status`): True (default)
            raises its error; False returns the result with ``status``
            :attr:`~thetahat.estimation.status.Status.DIVERGED`, its ``message`` and NaN
            rows from ``failed_at`` on.

        Returns
        -------
        EstimateResult
            Row k: the estimates after sample k's update; ``diagnostics`` is an
            :class:`EKFDiagnostics` (θ's standard deviation, NIS, σ).

        Raises
        ------
        NonFiniteError
            The filter diverged (``throw=True``): where, and, when the innovations before
            show it, that the model taken as exact does not fit the record (give q_x > 0 or
            use method 'guarded' or 'mle').
        """
        sys_ = self.system
        n, p = sys_.n, sys_.p
        t_, U, Y = check_record(t, u, y, m=sys_.m, r=sys_.r)
        st = self.init() if state0 is None else self._check_state(state0)
        sigma = (st.noise_std if st.noise_std is not None
                 else resolve_noise_std(self.noise_std, Y))
        s = np.concatenate([st.x_hat, st.theta_hat])
        P = np.array(st.P, dtype=np.float64, order="C")
        ts = stage2_set(sys_.require_parameter_set("stage 2"))
        k = self.kernels
        Q_x = self.q_x * np.eye(n)
        Ut = stage2_samples(U, self.hold, st.u_history)[0]
        nsub = self.substeps or choose_substeps(k.model, t_, Ut, Y, st.theta_hat, st.x_hat,
                                                sigma, hold=self.hold, h_rho=self.h_rho)
        pc, WT = Propagation(hold=self.hold, substeps=nsub, h_rho=self.h_rho).arrays()
        if st.k > 0 and st.u_prev is not None:
            U2 = np.ascontiguousarray(np.stack([st.u_prev, Ut[0]]), dtype=np.float64)
            k.predict(s, P, U2, 0, st.dt_prev, pc, WT, Q_x, np.empty((n, n)),
                      np.empty((n, p)))
        N = t_.shape[0]
        X, TH, SD, NIS = (np.empty((N, n)), np.empty((N, p)), np.empty((N, p)),
                          np.full(N, np.nan))
        bad = k.loop(s, P, Ut, Y, t_, 0, N, np.diag(sigma ** 2), ts.lo, ts.hi, ts.ell,
                     pc, WT, Q_x, X, TH, SD, NIS)
        stop = (None if bad < 0
                else RunStop(Status.DIVERGED, divergence_message(t_, bad, NIS, sys_.r), bad))
        res = stopped_result(t=t_, x_hat=X, theta_hat=TH,
                             phi_hat=model_phi_hat(sys_, U, Y, X, TH, stop),
                             skipped=missing_samples(Y),
                             diagnostics=EKFDiagnostics(theta_sd=SD, nis=NIS, noise_std=sigma,
                                                        substeps=nsub),
                             stop=stop, blank=(SD, NIS))
        return res.raise_for_status() if throw else res

    def __repr__(self) -> str:
        return (f"JointEKF(n={self.system.n}, p={self.system.p}, hold={self.hold!r}, "
                f"compiled={self.kernels.model.compiled})")
