"""The two-stage guarded estimator: the paper's guarantee with an EKF's efficiency.

* **Stage 1** — the paper's observer (3) with its update law, unchanged (an
  :class:`~thetahat.estimation.protocol.Estimator` whose states its ``estimate`` reads: the
  observer or its compiled form): Theorem 1's convergence from anywhere in Θ.
* **Stage 2** — the joint EKF's kernels on col(x, θ) (:mod:`~thetahat.estimation.statistical.ekf_kernels`), re-anchored
  at the times of a :class:`~thetahat.estimation.statistical.map_fit.FitSchedule` by the MAP fit of
  (x(t₀), θ) (the EKF then takes θ and P_θθ from the fit, cross-covariances zeroed).
* **The guard** of :mod:`~thetahat.estimation.statistical.guard`: the output keeps
  |θ̂ − θ| ≤ |θ̂_G − θ| + δ(t) and θ̂ ∈ Θ, with δ(t) built on evidence.

Unless given, the noise level is estimated from the first
:data:`~thetahat.estimation.statistical.noise_level.MIN_SAMPLES` samples (the EKF starts its updates
there), refined at :data:`SIGMA_SAMPLES` samples and refreshed by every fit from its window.
:meth:`run` applies each fit at the sample after its window (deterministic). In streaming use
(:meth:`step`) fits run in a worker process (:mod:`~thetahat.estimation.statistical.fit_worker`) and are
applied at the first ``step`` after they finish: a ``step`` never waits for a fit and shares
no lock with it; a fit that crashes or returns non-finite values is ignored with a
:class:`~thetahat.errors.ThetahatWarning` (:meth:`GuardedEstimator.stream_diagnostics`).

A run fails only where its own estimates are not finite (stage 2 is reset from stage 1 when it
is not finite): with ``throw=True`` its error is raised; with ``throw=False`` the result
carries the status and message and NaN rows from ``failed_at`` on
(:mod:`~thetahat.estimation.status`). A stage 1 that stops does not end the run: from that
sample the guard's band is Θ's full width, stage 2 and the fits go on (reset, when not
finite, from the start values), and a ThetahatWarning and the diagnostics'
``stage1_failed_at`` say that the paper's guarantee is gone from there.

What it may import: :mod:`thetahat.model`, the package's errors, the bottom of the
estimation wing (``protocol``, ``records``, ``status``), and every module of this room but the
other estimators' (``ekf``, ``mle``, ``trust``, ``crlb``); stage 1 is handed in, not imported.
"""

from __future__ import annotations

import concurrent.futures
import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...errors import (ArgumentTypeError, DimensionError, NonFiniteError, OptionError,
                      StateError, ThetahatError, ThetahatWarning, UpdateLawError)
from ...model.system import PerturbedLinearSystem
from ...progress import FitProgress
from ..hold import DEFAULT_HOLD
from ..observer.plan import DT_RTOL
from ..protocol import Diagnostics, EstimateResult, check_state, missing_samples, stream_sample
from ..records import check_record
from ..status import Status
from .common import (RunStop, joint_prior, model_phi_hat, resolve_noise_std, sample_interval,
                     start_values, stopped_result)
from .ekf_kernels import EKFKernels, ekf_kernels
from .guard import (GUARD_C, GUARD_DWELL, GUARD_KAPPA, GUARD_RHO_MAX, guarded_loop,
                    progress_init)
from .guarded_stream import SIGMA_SAMPLES, GuardedStream, StreamDiagnostics
from .input_hold import stage2_samples, streamable
from .map_fit import (REJECT_STEP_SE, FitResult, FitSchedule, fit_as_prior, fit_record,
                      why_not_applied)
from .noise_level import MIN_SAMPLES
from .plant_kernel import H_RHO, Propagation, choose_substeps, printed_kernels
from .stage2_set import stage2_set
from .window import WINDOW_MAX, Anchor, check_window, fit_window, resolve_window, windowed

__all__ = ["GuardedDiagnostics", "GuardedEstimator", "GuardedState"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class GuardedDiagnostics(Diagnostics):
    """What :meth:`GuardedEstimator.run` reports beyond the common estimates
    (``result.diagnostics``; the result's ``theta_hat`` is the guarded output, its ``x_hat``
    stage 2's x̂).

    Attributes
    ----------
    theta_stage1, theta_stage2 : ndarray (N, p)
        θ̂_G and θ̂₂.
    theta_sd : ndarray (N, p)
        Stage 2's √P_θθ.
    band : ndarray (N, p)
        δ(t): |θ̂ − θ̂_G| ≤ δ at every sample.
    clipped, reset : ndarray of bool (N,)
        Samples where the guard clipped stage 2 / reset it from stage 1.
    nis : ndarray (N,)
        Windowed normalised innovation squared of stage 2 (≈ 1 when consistent).
    fits : tuple of FitResult
        The MAP fits that came back, in order; stage 2 took those that are consistent
        (:attr:`FitResult.consistent`) and fitted (:meth:`FitResult.rejection`: converged,
        standard errors not grown by orders of magnitude); ``rejected`` says why the others
        were not.
    fit_samples : ndarray of int
        The last sample of each fit's window (where a consistent one was applied).
    noise_std : ndarray (r,)
        The last σ used.
    failures : tuple of str
        Fits that raised or came back non-finite, one sentence each (ignored, with a
        ThetahatWarning: stage 1 and the EKF go on).
    rejected : tuple of str
        The fits that came back but were not applied, one sentence each.
    substeps : int
        The RK4 sub-steps' accuracy floor stage 2 ran with at the end.
    stage1_failed_at : int or None
        The sample at which stage 1 stopped (its ``failed_at``), None when it ran to the end.
        From there ``theta_stage1`` is NaN, the guard's band is Θ's full width (the paper's
        guarantee is gone) and the guarded θ̂ is stage 2's and the fits', within Θ.
    stage1_message : str
        Stage 1's own message when it stopped ("" otherwise).
    """

    theta_stage1: FloatArray
    theta_stage2: FloatArray
    theta_sd: FloatArray
    band: FloatArray
    clipped: NDArray[np.bool_]
    reset: NDArray[np.bool_]
    nis: FloatArray
    fits: tuple[FitResult, ...]
    fit_samples: NDArray[np.int64]
    noise_std: FloatArray
    failures: tuple[str, ...] = ()
    rejected: tuple[str, ...] = ()
    substeps: int = 1
    stage1_failed_at: int | None = None
    stage1_message: str = ""

    @property
    def fits_rejected(self) -> int:
        """Fits that came back but were not applied (``rejected`` says why)."""
        return len(self.rejected)

    @property
    def fits_failed(self) -> int:
        """Fits that raised or came back non-finite (ignored)."""
        return len(self.failures)

    @property
    def disagreement(self) -> FloatArray:
        """θ̂₂ − θ̂_G over time, (N, p): a model-error alarm when it persists."""
        return self.theta_stage2 - self.theta_stage1

    @property
    def resets(self) -> int:
        """How many times stage 2 was reset from stage 1."""
        return int(self.reset.sum())

    @property
    def clipped_fraction(self) -> float:
        """Fraction of the samples where the guard clipped stage 2."""
        return float(self.clipped.mean())

    @property
    def fit_cost(self) -> FloatArray:
        """Each fit's cost per measurement (≈ 1 when the model and σ are right)."""
        return np.array([f.cost for f in self.fits])

    @property
    def fit_se(self) -> FloatArray:
        """Each fit's standard error of θ, (n_fits, p)."""
        return np.array([f.theta_se for f in self.fits]).reshape(len(self.fits), -1)

    def __repr__(self) -> str:
        return (f"GuardedDiagnostics(resets={self.resets}, "
                f"clipped={self.clipped_fraction:.3f}, fits={len(self.fits)}, "
                f"fits_rejected={self.fits_rejected}, fits_failed={self.fits_failed}, "
                + ("" if self.stage1_failed_at is None
                   else f"stage1_failed_at={self.stage1_failed_at}, ")
                + f"noise_std={self.noise_std})")


@dataclass(frozen=True, slots=True, eq=False)
class GuardedState:
    """The state of :class:`GuardedEstimator` (from :meth:`~GuardedEstimator.init` or
    :meth:`~GuardedEstimator.step`).

    Attributes
    ----------
    stage1 : ndarray
        Stage 1's (the observer's) state.
    x_hat0, theta_hat0 : ndarray (n,), (p,)
        Stage 2's start values (θ̂₀ in Θ).
    stream : GuardedStream or None
        The stream's shared data log, stage 2's (s, P) and pending fit (None before the first
        ``step``; :mod:`~thetahat.estimation.statistical.guarded_stream`): states of one
        stream share it, so step each state once, in order.
    theta_hat : ndarray (p,) or None
        The guarded θ̂ at the last sample stepped (None before the first ``step``).
    x_hat : ndarray (n,) or None
        Stage 2's x̂ there.
    theta_stage1, theta_stage2, band : ndarray (p,) or None
        θ̂_G, θ̂₂ and δ there.
    clipped, reset : bool
        The guard clipped stage 2 / reset it from stage 1 there.
    fits, fits_failed : int
        Fits back so far / ignored (see :meth:`GuardedEstimator.stream_diagnostics`).
    k : int
        Samples stepped (a state whose stream has moved on is refused).
    """

    stage1: Any
    x_hat0: FloatArray
    theta_hat0: FloatArray
    stream: GuardedStream | None = None
    theta_hat: FloatArray | None = None
    x_hat: FloatArray | None = None
    theta_stage1: FloatArray | None = None
    theta_stage2: FloatArray | None = None
    band: FloatArray | None = None
    clipped: bool = False
    reset: bool = False
    fits: int = 0
    fits_failed: int = 0
    k: int = 0

    def __repr__(self) -> str:
        return (f"GuardedState(theta_hat={self.theta_hat}, clipped={self.clipped}, "
                f"reset={self.reset}, fits={self.fits})")


@dataclass(frozen=True, slots=True, eq=False)
class GuardedEstimator:
    """Stage 1 (the paper) + stage 2 (EKF + MAP re-anchoring) + the evidence-based guard.

    Parameters
    ----------
    stage1 : ModifiedHighGainObserver or CompiledObserver
        The paper's estimator (an :class:`~thetahat.estimation.protocol.Estimator` whose
        state ``estimate`` reads); its ``system`` is stage 2's model unless ``system`` is
        given.
    system : PerturbedLinearSystem, optional
        Stage 2's model (symbolic g, any convex Θ).
    noise_std : optional
        σ of the output noise; default estimated from the data.
    schedule : FitSchedule, optional
        The re-anchoring fits (default :class:`FitSchedule`: all the data so far, each time
        the information has grown by √2; one with ``times`` fits at those times, in seconds).
    use_fits : bool
        False: no re-anchoring (stage 2 = the EKF alone).
    x_sd : float or array_like (n,), optional
        Prior standard deviation of x(0) for stage 2; default
        :func:`~thetahat.estimation.statistical.common.x_prior_sd` of x̂(0).
    kappa, c, rho_max, dwell : float
        The guard's constants (see :mod:`~thetahat.estimation.statistical.guard`); ``dwell`` a fraction
        of the samples so far (default :data:`~thetahat.estimation.statistical.guard.GUARD_DWELL`).
    q_x : float
        Stage 2's process-noise variance per sample on x (default 0: the model is exact).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        Stage 2's u between the samples (:mod:`~thetahat.estimation.hold`; default ``"smooth"``;
        ``"bandlimited"`` for :meth:`run` only); stage 1's is its own (a model file gives
        both the file's).
    substeps : int, optional
        Stage 2's RK4 sub-steps' accuracy floor; default: chosen per record at the start
        values (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`; in
        :meth:`step`, by each fit on its window).
    h_rho : float
        RK4 sub-step bound (see :mod:`~thetahat.estimation.statistical.plant_kernel`).
    compiled : bool, optional
        numba kernels (default: when installed).
    fit_executor : concurrent.futures.Executor, optional
        Where streaming fits run (anything with ``submit(fn, *args) -> Future``); default
        the shared worker process of :func:`~thetahat.estimation.statistical.fit_worker.default_executor`.
        :meth:`run` always fits in the caller.
    window : {None, "auto"} or int
        The fits: None (default) of all the data so far; W or ``"auto"``: bounded fits
        (:mod:`~thetahat.estimation.statistical.window`), stage 2's posterior at the window's
        start the arrival cost, in :meth:`run` and in :meth:`step` (whose data log then holds
        at most W + 1 samples plus those stepped while a fit runs:
        :mod:`~thetahat.estimation.statistical.guarded_stream`). Not with ``times``.
    window_max : int
        The longest ``"auto"`` window (:data:`~.window.WINDOW_MAX` samples).

    Notes
    -----
    An :class:`~thetahat.estimation.protocol.Estimator`: :meth:`init` gives a
    :class:`GuardedState`, :meth:`step` streams, :meth:`run` runs a record; results carry
    :class:`GuardedDiagnostics`.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> est = lugre.estimator("guarded", compiled=False)
    >>> data = lugre.simulate(seed=0, t_end=0.3)
    >>> res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    >>> res.theta_hat.shape, bool(abs(res.theta_hat[-1, 0] - 0.28) < 0.01)
    ((301, 1), True)
    """

    stage1: Any
    system: PerturbedLinearSystem | None = None
    noise_std: ArrayLike | None = None
    schedule: FitSchedule | None = field(default=None)
    use_fits: bool = True
    x_sd: ArrayLike | None = None
    kappa: float = GUARD_KAPPA
    c: float = GUARD_C
    rho_max: float = GUARD_RHO_MAX
    dwell: float = GUARD_DWELL
    q_x: float = 0.0
    hold: str = DEFAULT_HOLD
    substeps: int | None = None
    h_rho: float = H_RHO
    compiled: bool | None = None
    fit_executor: concurrent.futures.Executor | None = None
    window: int | str | None = None
    window_max: int = WINDOW_MAX

    def __post_init__(self) -> None:
        from ..protocol import Estimator
        if not isinstance(self.stage1, Estimator):
            raise ArgumentTypeError(
                f"stage1 must be an estimator with init, step and run (the paper's observer: "
                f"a ModifiedHighGainObserver or its CompiledObserver); got "
                f"{type(self.stage1).__name__}. For a model file use "
                "thetahat.modelfile.build_estimator(spec, method='guarded').")
        if self.system is None and not isinstance(getattr(self.stage1, "system", None),
                                                  PerturbedLinearSystem):
            raise ArgumentTypeError("stage 2 needs a model: give system=, or a stage1 with a "
                                    "PerturbedLinearSystem as its system.")
        Propagation(hold=self.hold, substeps=self.substeps or 1, h_rho=self.h_rho)
        check_window("GuardedEstimator", self.window, self.window_max, self.model)
        if self.window is not None and getattr(self.schedule, "times", None) is not None:
            raise OptionError("GuardedEstimator: window bounds the information schedule's "
                              "fits; a schedule with times has its blocks: give one.")

    # ------------------------------------------------------------------ parts
    @property
    def model(self) -> PerturbedLinearSystem:
        """Stage 2's model."""
        return self.system if self.system is not None else self.stage1.system

    @property
    def kernels(self) -> EKFKernels:
        return ekf_kernels(self.model, compiled=self.compiled)

    @property
    def fit_schedule(self) -> FitSchedule | None:
        if not self.use_fits:
            return None
        if self.schedule is not None:
            return replace(self.schedule, hold=self.hold).given_substeps(self.substeps)
        return FitSchedule(system=self.model, x_sd=self.x_sd, noise_std=self.noise_std,
                           hold=self.hold, h_rho=self.h_rho,
                           compiled=self.compiled).given_substeps(self.substeps)

    def _loop(self) -> Any:
        k = self.kernels
        loop = _LOOPS.get(k)
        if loop is None:
            loop = _LOOPS[k] = _guard_loop(k)
        return loop

    def _prior(self, x_hat0: FloatArray, theta_hat0: FloatArray
               ) -> tuple[FloatArray, FloatArray]:
        """Stage 2's (s0, P0) (:func:`~thetahat.estimation.statistical.common.joint_prior`)."""
        return joint_prior(self.model, x_hat0, theta_hat0, x_sd=self.x_sd)

    @staticmethod
    def _fit_or_none(sched: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
                     k1: int, prev: FitResult | None, prior0: tuple[FloatArray, FloatArray],
                     final: bool | None, failures: list[str],
                     anchor: Anchor | None = None) -> FitResult | None:
        """The fit due at k1 (``final`` None: a schedule with times; ``anchor`` (k0, s, P, σ):
        the window k0 … k1 − 1 with N(s, P) at k0 as arrival cost), or None with the reason
        appended to ``failures`` and a warning when it raised or came back non-finite."""
        try:
            if anchor is not None:
                fit = fit_window(sched, t, U, Y, k0=anchor[0], k1=k1, s0=anchor[1],
                                 P0=anchor[2], noise_std=anchor[3], final=bool(final))
            elif final is None:
                fit = sched.fit(t, U, Y, k1, prev, prior0)
            else:
                fit = fit_record(sched, t, U, Y, k1, prev, prior0, final=final)
        except (ThetahatError, ArithmeticError, np.linalg.LinAlgError) as exc:
            why = (f"the fit of samples {0 if anchor is None else anchor[0]}…{k1 - 1} "
                   f"raised {type(exc).__name__}: {exc}")
        else:
            if fit.finite:
                return fit
            why = f"the fit of samples {fit.k0}…{fit.k1 - 1} came back non-finite"
        failures.append(why)
        warnings.warn(f"GuardedEstimator.run: a stage-2 fit was ignored: {why}. Stage 1 and "
                      "the EKF go on.", ThetahatWarning, stacklevel=3)
        return None

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None
             ) -> GuardedState:
        """Initial state of both stages.

        Parameters
        ----------
        x_hat0 : array_like (n,), optional
            Default zeros.
        theta_hat0 : array_like (p,), optional
            In Θ; default the centre of Θ.

        Returns
        -------
        GuardedState
            Stage 1's state and stage 2's start values.
        """
        x0, th0 = start_values(self.model, x_hat0, theta_hat0)
        s1 = self.stage1.init(x_hat0=x0, theta_hat0=th0)
        return GuardedState(stage1=s1, x_hat0=x0, theta_hat0=th0)

    # ------------------------------------------------------------------ offline
    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            state0: GuardedState | None = None, throw: bool = True,
            fit_progress: FitProgress | None = None) -> EstimateResult:
        """Run both stages and the guard over a record.

        Parameters
        ----------
        t : array_like (N,)
        u : array_like (N, m) or (N,)
        y : array_like (N, r) or (N,)
        state0 : GuardedState, optional
            From :meth:`init` (default ``init()``); a record starts a new experiment, so a
            state that has been stepped is refused.
        throw : bool
            What a failure of the run does (:mod:`~thetahat.estimation.status`): True
            (default) raises its error; False returns the result with its ``status`` and
            ``message`` and NaN rows from ``failed_at`` on. The run fails only when its own
            output (θ̂, x̂ or φ̂) is not finite
            (:attr:`~thetahat.estimation.status.Status.DIVERGED`). A failure of stage 1 does
            not end it: from stage 1's ``failed_at`` on, stage 2 and the fits go on with the
            guard's band at Θ's full width (the paper's guarantee is gone, and a
            ThetahatWarning says so; ``diagnostics.stage1_failed_at`` and ``stage1_message``
            keep stage 1's report). Stage 2 is reset from stage 1 when it is not finite (from
            the start values once stage 1 has stopped); a failed fit is ignored.
        fit_progress : callable, optional
            ``fit_progress(done, total)`` (:data:`thetahat.progress.FitProgress`), called in
            the caller's thread once stage 1 has run: ``(0, total)`` before stage 2, then
            after each re-anchoring fit (applied, rejected or failed alike) ``(done,
            total)``. ``total`` is the number of fits the schedule places on the samples
            stage 1 gave, known before the first (0 without fits: ``use_fits=False`` or a
            record too short for one); the last call is ``(total, total)``. An exception it
            raises (a ``KeyboardInterrupt`` too) ends the run and propagates unchanged. It
            does not change the estimates.

        Returns
        -------
        EstimateResult
            ``theta_hat`` the guarded output, ``x_hat`` stage 2's; ``diagnostics`` a
            :class:`GuardedDiagnostics` (both stages, the guard's band, the fits).

        Raises
        ------
        OptionError
            ``state0`` has been stepped (continue that stream with :meth:`step`).
        NonFiniteError
            ``throw=True`` and the guarded output is not finite.
        """
        sys_ = self.model
        t_, U, Y = check_record(t, u, y, m=sys_.m, r=sys_.r)
        st0 = self.init() if state0 is None else self._check_state(state0)
        if st0.stream is not None:
            raise OptionError("GuardedEstimator.run starts an experiment from init(); this "
                              "state0 has been stepped: continue its stream with step.")
        run = _OfflineRun(self, t_, U, Y, st0)
        run.filter(t_.shape[0], fit_progress)
        res = run.result(run.stop())
        return res.raise_for_status() if throw else res

    # ------------------------------------------------------------------ streaming
    def step(self, state: GuardedState, u: ArrayLike | None, y: ArrayLike, dt: float
             ) -> GuardedState:
        """Process the current samples (u, y) and advance stage 1 by ``dt``; never waits.

        Parameters
        ----------
        state : GuardedState
            From :meth:`init` or the previous ``step``. States of one stream share its data
            log and fit worker: step each state once, in order.
        u : array_like (m,)
        y : array_like (r,); NaN: no measurement update.
        dt : float
            Time to the next sample, > 0.

        Returns
        -------
        GuardedState
            The next state, with the estimates at the current sample (row k of :meth:`run`
            after k + 1 steps when no fit is made): ``theta_hat`` (p,), ``x_hat`` (n,),
            ``theta_stage1``, ``theta_stage2``, ``band``, ``clipped``, ``reset``, ``fits``
            (the number of fits back so far), ``fits_failed`` (ignored fits; see
            :meth:`stream_diagnostics`). A stage 1 whose step fails (or whose estimate is not
            finite) is lost from that sample on, as in :meth:`run`: a ThetahatWarning,
            ``theta_stage1`` NaN, the band Θ's full width,
            ``stream_diagnostics(state).stage1_failed_at``; its state is kept as it was. A
            sample stage 1 refuses (its NaN policy) raises, as before.
        """
        sys_ = self.model
        n, m, p = sys_.n, sys_.m, sys_.p
        sh = getattr(state, "stream", None)
        if sh is None or state is not sh.last:      # (the state the stream returned: checked)
            state = self._check_state(state)
        # own, writable copies (a read-only view would need its own compiled specialisation)
        u_, y_, h = stream_sample(sys_, u, y, dt)
        if sh is None:
            sh = self._start_stream(state, h)
        elif sh.owner is not self:
            raise StateError("GuardedEstimator.step: this state's stream was started by "
                             "another GuardedEstimator (its log, guard and fits are that "
                             "estimator's); step it with that one, or start a stream of this "
                             "one from init().")
        elif sh.k != state.k:
            raise StateError(f"GuardedEstimator.step: this state is not the latest of its "
                             f"stream (it has {state.k} samples, its stream {sh.k}: it was "
                             f"stepped already); step each state once, in order, from "
                             f"init().")
        k = sh.k
        if k == 0:
            sh.configure(self.kappa, self.c, self.rho_max, self.dwell)
        thG, xG = state.theta_hat0, state.x_hat0      # stage 1 lost: the start values (run's)
        s1, lost = state.stage1, None               # (kept as it was when stage 1 is lost)
        if sh.stage1_failed_at is None:
            # x̂, θ̂, x̂₂ at this sample (without φ̂, unused) and stage 1's next state, the
            # samples checked against its NaN policy (an error is the caller's). A step that
            # fails loses stage 1 after this sample: read the estimates alone (which raise
            # what was the caller's)
            try:
                x1, th1, x2, s1 = sh.step_stage1(state.stage1, u_, y_, h)
            except (NonFiniteError, UpdateLawError) as exc:
                x1, th1, x2 = sh.read_stage1(state.stage1, u_, y_)
                lost = exc
            th1 = np.asarray(th1, dtype=np.float64).reshape(p)
            x1 = np.asarray(x1 if x2 is None else x2, dtype=np.float64).reshape(n)
            if all(map(math.isfinite, th1.tolist())) and all(map(math.isfinite, x1.tolist())):
                thG, xG = th1, x1
            else:
                s1, lost = state.stage1, None
                _lose_stage1(sh, k, NonFiniteError(f"stage 1's estimate at sample {k} is not "
                                                   "finite"))
        ut, sh.u_history = stage2_samples(u_.reshape(1, m), sh.hold,      # stage 2's samples
                                          sh.u_history)
        sh.record(k, ut[0], y_, h)
        sh.poll_fit()
        # the loop over one sample: row 0 the previous sample (u held, no y) after the first
        k0 = 0 if k == 0 else 1
        U2, Y2, tt, TH2, XG2 = sh.step_in
        if k:
            U2[0], Y2[0], tt[1] = sh.u_prev, np.nan, sh.dt_prev
        U2[k0], Y2[k0], TH2[:], XG2[:] = ut[0], y_, thG, xG
        ins, out = ((sh.step_in, sh.step_out) if k else
                    (tuple(a[:1] for a in sh.step_in), tuple(a[:1] for a in sh.step_out)))
        if k == 0:
            sh.pst = progress_init(thG)
        TH, TH2o, X2, SD2, BAND, clip, rst, nis = out
        sh.loop(sh.s, sh.P, sh.P0, *ins[:3], k0, k0 + 1, k - k0, sh.R, sh.lo, sh.hi,
                sh.ell, sh.pc, sh.WT, sh.Q_x, *ins[3:], sh.pst, sh.gst, sh.cfg, *out)
        if lost is not None:
            _lose_stage1(sh, k + 1, lost)
        sh.refresh_sigma(k)
        sh.u_prev, sh.dt_prev, sh.k = ut[0], h, k + 1
        sh.maybe_submit()
        sh.last = GuardedState(stage1=s1, x_hat0=state.x_hat0, theta_hat0=state.theta_hat0,
                            stream=sh, theta_hat=TH[k0].copy(), x_hat=X2[k0].copy(),
                            theta_stage1=(thG.copy() if sh.stage1_failed_at is None
                                          or k < sh.stage1_failed_at else np.full(p, np.nan)),
                            theta_stage2=TH2o[k0].copy(),
                            band=BAND[k0].copy(), clipped=bool(clip[k0]),
                            reset=bool(rst[k0]), fits=len(sh.fits),
                            fits_failed=len(sh.failures), k=k + 1)
        return sh.last

    def stream_diagnostics(self, state: GuardedState) -> StreamDiagnostics:
        """The fits of the stream that ``state`` belongs to (from :meth:`step`).

        Parameters
        ----------
        state : GuardedState
            A state returned by :meth:`step`.

        Returns
        -------
        StreamDiagnostics
        """
        sh = state.stream
        if sh is None:
            return StreamDiagnostics(fits=(), fit_samples=np.zeros((0, 2), np.int64),
                                     fit_seconds=np.zeros(0), failures=(), pending=False)
        return sh.diagnostics()

    def _start_stream(self, state: GuardedState, dt: float) -> GuardedStream:
        """The stream of a state that has not been stepped yet (its data log, stage 2 at its
        prior, the fit worker started when fits run)."""
        sched = self.fit_schedule
        s0, P0 = self._prior(state.x_hat0, state.theta_hat0)
        stream = GuardedStream.start(self.model, s0, P0, q_x=self.q_x,
                                     noise_std=self.noise_std, schedule=sched,
                                     prior0=(sched.initial_prior(state.x_hat0,
                                                                 state.theta_hat0)
                                             if sched else None),
                                     executor=self.fit_executor,
                                     hold=streamable(self.hold, "GuardedEstimator"),
                                     h_rho=self.h_rho, substeps=self.substeps,
                                     window=self.window, window_max=self.window_max)
        stream.owner = self
        stream.loop = self._loop()
        stream.read_stage1, stream.step_stage1, stream.stage1_backend = _stage1_calls(
            self.stage1, dt)
        return stream

    def _check_state(self, state: Any) -> GuardedState:
        """``state`` if it is a :class:`GuardedState` of this model (:func:`check_state`)."""
        n, p = self.model.n, self.model.p
        return check_state("GuardedEstimator", state, GuardedState,
                           {"x_hat0": (n,), "theta_hat0": (p,), "theta_hat": (p,),
                            "x_hat": (n,)})

    def __repr__(self) -> str:
        return (f"GuardedEstimator(stage1={type(self.stage1).__name__}, n={self.model.n}, "
                f"p={self.model.p}, fits={'on' if self.use_fits else 'off'})")


class _OfflineRun:
    """Stage 2, the guard and the fits of :meth:`GuardedEstimator.run` over one record.

    The record is run in segments: between σ's refreshes (at :data:`MIN_SAMPLES` and
    :data:`SIGMA_SAMPLES` samples, when σ is estimated), the scheduled fits, each applied
    at the sample after its window, and the sample where stage 1 stopped, if it did; the
    arrays are written in place. From that sample on the loop reads the start values in place
    of stage 1's θ̂_G and x̂ (what a non-finite stage 2 is reset to) and the guard's ρ_max is
    0, so that its band δ_G is Θ's full width (no evidence of contraction: stage 1 gives none).
    """

    def __init__(self, est: GuardedEstimator, t: FloatArray, U: FloatArray, Y: FloatArray,
                 st0: GuardedState) -> None:
        sys_ = est.model
        n, p, N = sys_.n, sys_.p, t.shape[0]
        self.est, self.system, self.t, self.U, self.Y = est, sys_, t, U, Y
        # stage 1 over the record; its result is dropped once its θ̂ and x̂ are copied below
        # (a record's x̂, x̂₂ and φ̂ less to hold during the fits: nothing else refers to it)
        res1 = est.stage1.run(t, U, Y, state0=st0.stage1, throw=False)
        self.Us = stage2_samples(U, est.hold)[0]              # stage 2's input samples
        xs = res1.x_hat if res1.x_hat_refined is None else res1.x_hat_refined
        # writable C copies (the compiled loop's array type); stage 1's report keeps its NaN
        # rows from where it stopped, the loop's copy holds the start values there
        self.thG = np.array(res1.theta_hat, dtype=np.float64, order="C")
        self.xG = np.array(xs, dtype=np.float64, order="C")
        self.theta_stage1 = self.thG
        self.lost, self.lost_message = res1.failed_at, res1.message
        del res1, xs
        if self.lost is not None:
            self.theta_stage1 = self.thG.copy()
            self.thG[self.lost:] = st0.theta_hat0
            self.xG[self.lost:] = st0.x_hat0
        self.estimate_sigma = est.noise_std is None
        k_first = MIN_SAMPLES if self.estimate_sigma else 0
        self.sigma = resolve_noise_std(est.noise_std, Y[:max(k_first, MIN_SAMPLES)])
        self.R = np.diag(self.sigma ** 2)
        self.s, self.P0 = est._prior(st0.x_hat0, st0.theta_hat0)
        self.P = self.P0.copy()
        self.ts = stage2_set(sys_.require_parameter_set("stage 2"))
        self.out = {name: np.empty((N, w)) for name, w in
                    (("TH", p), ("TH2", p), ("X2", n), ("SD2", p), ("BAND", p))}
        self.CLIP, self.RESET = np.zeros(N, bool), np.zeros(N, bool)
        self.NIS = np.full(N, np.nan)
        self.pst = progress_init(self.thG[0])
        self.gst = np.array([0.0, 1.0, float(k_first)])
        # (κ, c, ρ_max, dwell, σ₂ cap; θ_F, κ s_F of the latest consistent fit: none yet)
        self.cfg = np.concatenate([[est.kappa, est.c, est.rho_max, est.dwell],
                                   np.sqrt(np.diag(self.P0)[n:]), np.zeros(p), np.full(p, -1.0)])
        self.Q_x = est.q_x * np.eye(n)
        self.fits: list[FitResult] = []
        self.fit_at: list[int] = []
        self.failures: list[str] = []
        self.rejected: list[str] = []
        self.applied: FitResult | None = None
        self.substeps = est.substeps or self._choose_substeps(st0)
        self.pc, self.WT = Propagation(hold=est.hold, substeps=self.substeps,
                                       h_rho=est.h_rho).arrays()
        sched = est.fit_schedule
        if sched is not None:
            sched = replace(sched, substeps=self.substeps)
        self.prior0 = (sched.initial_prior(st0.x_hat0, st0.theta_hat0) if sched else None)
        # the default fits: all the data so far, at the sample counts where the information
        # has grown by INFO_GROWTH, the last on all samples but the last (whose output then
        # follows it); a schedule with times keeps its times (seconds) and windows
        self.by_samples = sched is not None and sched.times is None
        self.ks: list[int] = []
        self.W: int | None = None
        if sched is not None and self.by_samples:
            sched = replace(sched, full_window=math.inf)
            least = 3 if est.noise_std is not None else MIN_SAMPLES
            self.ks = [k1 for k1 in sched.fit_samples(t[:N - 1], least=least)
                       if MIN_SAMPLES <= k1 < N]
            self.W = resolve_window(est.window, est.window_max, replace(
                sched, substeps=est.substeps), t, self.Us, Y, sched.initial_prior(
                    st0.x_hat0, st0.theta_hat0))
        self.ks = windowed(self.ks, self.W)
        self.anchor: Anchor | None = None
        self.sched = sched

    def _choose_substeps(self, st0: GuardedState) -> int:
        """The record's sub-steps at the start values (1 when σ cannot be had yet)."""
        est = self.est
        if est.noise_std is None and self.Y.shape[0] < MIN_SAMPLES:
            return 1
        sigma = resolve_noise_std(est.noise_std, self.Y)
        return choose_substeps(est.kernels.model, self.t, self.Us, self.Y, st0.theta_hat0,
                               st0.x_hat0, sigma, hold=est.hold, h_rho=est.h_rho)

    def filter(self, rows: int, fit_progress: FitProgress | None = None) -> None:
        """Stage 2 and the guard over rows 0 … rows − 1 (those stage 1 gave), the fits applied
        as they fall due; ``fit_progress(done, total)`` before the first and after each."""
        done = total = 0
        if fit_progress is not None:            # the schedule's fits, counted in advance
            total = sum(fit for _, _, fit in self._segments(rows))
            fit_progress(0, total)
        for k, k_next, fit in self._segments(rows):
            if self.estimate_sigma and k in (MIN_SAMPLES, SIGMA_SAMPLES):   # σ̂ from
                self.sigma = resolve_noise_std(None, self.Y[:k])   # MIN_SAMPLES, refined
                self.R = np.diag(self.sigma ** 2)                  # at SIGMA_SAMPLES
            if k == self.lost:
                self._stage1_lost()
            self._samples(k, k_next)
            if fit:
                self._fit(k_next)
                done += 1
                if fit_progress is not None:     # outside _fit: the callback's errors pass
                    fit_progress(done, total)

    def _stage1_lost(self) -> None:
        """Stage 1 stopped at this sample: the band from here is Θ's width (ρ_max = 0), and
        the user is told."""
        k = self.lost
        assert k is not None
        _without_stage1(self.cfg, f"run: stage 1 stopped at t[{k}] = {self.t[k]:.6g}",
                    self.lost_message, stacklevel=4)

    def _segments(self, rows: int) -> Iterator[tuple[int, int, bool]]:
        """(k, k_next, fit): stage 2 runs samples k … k_next − 1, then (fit) the fit due
        there; the segments end at σ's refreshes, at the scheduled fits and where stage 1
        stopped. A pure walk of the schedule: :meth:`filter` follows it, and counts its fits
        in advance."""
        k = j = 0
        while k < rows:
            k_next = rows
            if self.estimate_sigma and k < SIGMA_SAMPLES:
                k_next = MIN_SAMPLES if k < MIN_SAMPLES else SIGMA_SAMPLES
            if self.lost is not None and k < self.lost:
                k_next = min(k_next, self.lost)
            j, k_fit = self._next_fit(k, j)
            k_next = min(k_fit, rows, k_next)
            due = self.sched is not None and k_next == k_fit < rows
            yield k, k_next, due and MIN_SAMPLES <= k_next and self.prior0 is not None
            if due and not self.by_samples:
                j += 1
            k = k_next

    def _next_fit(self, k: int, j: int) -> tuple[int, int]:
        """(j, k₁): the next scheduled fit after sample k and the samples it covers (N: none)."""
        t, sched = self.t, self.sched
        N = t.shape[0]
        if sched is None:
            return j, N
        times = sched.times
        if times is None:                        # by samples
            while j < len(self.ks) and self.ks[j] <= k:
                j += 1
            return j, self.ks[j] if j < len(self.ks) else N
        while times(j) <= t[k] - t[0]:
            j += 1
        return j, int(np.searchsorted(t - t[0], times(j) + 1e-12, side="right"))

    def _samples(self, k0: int, k1: int) -> None:
        """The compiled loop over samples k0 … k1 − 1."""
        o, ts, est = self.out, self.ts, self.est
        est._loop()(self.s, self.P, self.P0, self.Us, self.Y, self.t, k0, k1, 0, self.R, ts.lo,
                    ts.hi, ts.ell, self.pc, self.WT, self.Q_x, self.thG, self.xG, self.pst,
                    self.gst, self.cfg, o["TH"], o["TH2"], o["X2"], o["SD2"], o["BAND"],
                    self.CLIP, self.RESET, self.NIS)

    def _fit(self, k1: int) -> None:
        """The fit due after sample k1 − 1; a consistent one that fitted re-anchors stage 2
        (:meth:`FitResult.rejection`: never a fit that did not converge)."""
        sched, prior0, est = self.sched, self.prior0, self.est
        if sched is None or prior0 is None:
            return
        prev = self.fits[-1] if self.fits else None
        fit = est._fit_or_none(sched, self.t, self.Us, self.Y, k1, prev, prior0,
                               k1 == self.ks[-1] if self.by_samples else None, self.failures,
                               self.anchor if self.W is not None and k1 > self.W else None)
        self._take(fit, k1)
        if self.W is not None and k1 >= self.W:  # the next window starts at this sample
            self.anchor = (k1 - 1, self.s.copy(), self.P.copy(), self.sigma.copy())

    def _take(self, fit: FitResult | None, k1: int) -> None:
        """Apply the fit due after sample k1 − 1 if it may be (the reasons of :meth:`_fit`)."""
        est = self.est
        if fit is None:
            return
        self.fits.append(fit)
        self.fit_at.append(k1 - 1)
        why = why_not_applied(fit, self.applied)
        if why is not None:
            self.rejected.append(why)
        else:
            self.applied = fit
            if fit.substeps != self.substeps:   # the final fit found more were needed
                self.substeps = fit.substeps
                self.pc, self.WT = Propagation(hold=est.hold, substeps=fit.substeps,
                                               h_rho=est.h_rho).arrays()
            # the fit ends at this very sample: take (x, θ) and their joint covariance;
            # stage 2 carries the model error as the fit found it (none: q = 0)
            s_fit, P_fit, self.R, self.Q_x = fit_as_prior(
                self.system, fit, sample_interval(self.t[fit.k0:k1]), est.q_x)
            self.s[:], self.P[:, :] = s_fit, P_fit
            p = fit.theta.shape[0]
            self.cfg[4 + p:4 + 2 * p] = fit.theta
            self.cfg[4 + 2 * p:] = est.kappa * fit.theta_se
            self.sigma = fit.noise_std

    def stop(self) -> RunStop | None:
        """Where the run stopped: the first sample whose guarded θ̂ or stage 2's x̂ is not
        finite (None: it ran to the end)."""
        o = self.out
        bad = ~(np.isfinite(o["TH"]).all(axis=1) & np.isfinite(o["X2"]).all(axis=1))
        if not bad.any():
            return None
        k = int(np.argmax(bad))
        if self.lost is not None and self.lost <= k:
            why = (f"stage 1 stopped at t[{self.lost}] ({self.lost_message.rstrip('.')}) and "
                   "stage 2 could not go on without it")
        else:
            why = "stage 2 and its resets from stage 1 overflowed"
        return RunStop(Status.DIVERGED, f"the guarded output became non-finite at t[{k}] = "
                       f"{self.t[k]:.6g}: {why}; check the data scaling, the noise level and "
                       "stage 1's gains.", k)

    def result(self, stop: RunStop | None) -> EstimateResult:
        """The estimates and :class:`GuardedDiagnostics` (NaN rows from ``stop.at`` on); a
        warning when the last fit did not converge and was not applied (earlier ones are in
        the diagnostics' ``rejected``: a later fit of more data took their place)."""
        o = self.out
        last = self.fits[-1] if self.fits else None
        if (last is not None and last is not self.applied and last.consistent
                and not last.step_se <= REJECT_STEP_SE):
            warnings.warn(f"GuardedEstimator.run: the last stage-2 fit was not applied: "
                          f"{self.rejected[-1]}. θ̂ is the EKF's, carried on from the last fit "
                          "applied; a longer record or a narrower Θ helps the fit converge.",
                          ThetahatWarning, stacklevel=3)
        diag = GuardedDiagnostics(theta_stage1=self.theta_stage1, theta_stage2=o["TH2"],
                                  theta_sd=o["SD2"], band=o["BAND"], clipped=self.CLIP,
                                  reset=self.RESET, nis=self.NIS, fits=tuple(self.fits),
                                  fit_samples=np.array(self.fit_at, dtype=np.int64),
                                  noise_std=self.sigma, failures=tuple(self.failures),
                                  rejected=tuple(self.rejected), substeps=self.substeps,
                                  stage1_failed_at=self.lost,
                                  stage1_message=self.lost_message if self.lost is not None
                                  else "")
        return stopped_result(t=self.t, x_hat=o["X2"], theta_hat=o["TH"],
                              phi_hat=model_phi_hat(self.system, self.U, self.Y, o["X2"],
                                                    o["TH"], stop),
                              skipped=missing_samples(self.Y), diagnostics=diag, stop=stop,
                              blank=(self.theta_stage1, o["TH2"], o["SD2"], o["BAND"],
                                     self.NIS))


def _stage1_calls(stage1: Any, dt: float) -> tuple[Any, Any, str]:
    """Stage 1's ``(state, u, y) -> (x̂, θ̂, x̂₂)`` and ``(state, u, y, dt) -> (x̂, θ̂, x̂₂,
    next state)``, looked up once per stream, and the name of what steps it: its
    ``read_estimates`` (no φ̂) and ``read_and_step`` (one check of the samples and the
    state) when it has them, else made of its ``estimate`` and ``step``. A paper's observer
    in NumPy (a model file's) steps on the fastest back end installed for the stream's first
    ``dt`` (:func:`_fast_stage1`), and on its own ``step`` at any other ``dt``."""
    fast = _fast_stage1(stage1, dt)
    if fast is not None:
        own = stage1.read_and_step
        fast_step = fast.read_and_step

        def fast_or_own(state: Any, u: FloatArray, y: FloatArray,
                        h: float) -> tuple[Any, Any, Any, Any]:
            if abs(h - dt) <= DT_RTOL * dt:
                return fast_step(state, u, y, h)
            return own(state, u, y, h)
        return stage1.read_estimates, fast_or_own, type(fast).__name__
    read = getattr(stage1, "read_estimates", None)
    if read is None:
        def read(state: Any, u: FloatArray, y: FloatArray) -> tuple[Any, Any, Any]:
            est1 = stage1.estimate(state, u, y)
            return est1.x_hat, est1.theta_hat, est1.x_hat_refined
    read_and_step = getattr(stage1, "read_and_step", None)
    if read_and_step is None:
        def read_and_step(state: Any, u: FloatArray, y: FloatArray,
                          dt: float) -> tuple[Any, Any, Any, Any]:
            return (*read(state, u, y), stage1.step(state, u, y, dt))
    return read, read_and_step, type(stage1).__name__


def _fast_stage1(stage1: Any, dt: float) -> Any:
    """The fastest back end that takes ``stage1`` for steps of
    ``dt`` (:func:`~thetahat.estimation.drive.runner`: the C printed from the formulas, else
    numba's kernel; the same numbers to rounding, the conformance tests), or None: stage 1 is
    not a :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver` in NumPy,
    its ``compiled`` is False, or no back end takes it. Without it a model file's stream ran
    stage 1's step in NumPy: 430 µs of a 450 µs guarded step on LuGre's file."""
    from ..drive import runner
    from ..observer.observer import ModifiedHighGainObserver
    if type(stage1) is not ModifiedHighGainObserver or stage1.compiled is False:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ThetahatWarning)   # none: stage 1's own step
        fast = runner(stage1, (0.0, dt), compiled=True)
    if fast is stage1 or not hasattr(fast, "read_and_step"):
        return None
    return fast


def _without_stage1(cfg: FloatArray, where: str, message: str, *, stacklevel: int) -> None:
    """Stage 1 stopped: the guard's ρ_max (``cfg[2]``) is 0 from here, so that its band δ_G
    is Θ's full width, and a ThetahatWarning says so (``where``: "run: stage 1 stopped at
    t[k] = …" or "step: … at sample k"; ``message``: stage 1's own; ``stacklevel`` as for
    :func:`warnings.warn`, counted from the caller)."""
    cfg[2] = 0.0
    warnings.warn(f"GuardedEstimator.{where} ({message.rstrip('.')}). From there the guarded "
                  "θ̂ is stage 2's and the fits', kept in Θ, without the paper's guarantee (the "
                  "guard's band is Θ's full width); fix stage 1 (its gains, Γ, the data "
                  "scaling) to have the guarantee back.", ThetahatWarning,
                  stacklevel=stacklevel + 1)


def _lose_stage1(sh: GuardedStream, k: int, exc: Exception) -> None:
    """A stream's stage 1 failed: lost from sample k on, as in a run."""
    sh.stage1_failed_at, sh.stage1_message = k, str(exc)
    _without_stage1(sh.cfg, f"step: stage 1 stopped at sample {k}", str(exc), stacklevel=3)


_LOOPS: dict[Any, Any] = {}


def _guard_loop(k: EKFKernels) -> Any:
    """:func:`~thetahat.estimation.statistical.guard.guarded_loop` printed over the EKF's
    kernels (their module's ``predict``, ``update`` and ``project``; a ConvexSet's, whose
    kernels run uncompiled in a module instance of their own, assigned into one of its own)."""
    names = {"predict": k.predict, "update": k.update, "project": k.project}
    doc = ("Printed by thetahat.estimation.statistical.guarded: the guard's loop over one "
           "model's EKF; do not edit (content-addressed).")
    if k.printed:
        mod, (name,) = printed_kernels("thetahat_guard", doc, [guarded_loop], names,
                                       k.model.compiled)
    else:
        mod, (name,) = printed_kernels("thetahat_guard", doc, [guarded_loop],
                                       {key: key for key in names}, False,
                                       constants={key: "None" for key in names}, fresh=True)
        for key, fn in names.items():
            setattr(mod, key, fn)
    return getattr(mod, name)
