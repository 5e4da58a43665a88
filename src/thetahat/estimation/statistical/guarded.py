"""The two-stage guarded estimator: the paper's guarantee with an EKF's efficiency.

* **Stage 1** — the paper's observer (3) with its update law, unchanged (an
  :class:`~thetahat.estimation.protocol.Estimator` whose states its ``estimate`` reads: the
  observer or its compiled form): Theorem 1's convergence from anywhere in Θ.
* **Stage 2** — :class:`~thetahat.estimation.statistical.ekf.JointEKF`'s kernels on col(x, θ), re-anchored
  at the times of a :class:`~thetahat.estimation.statistical.mle.FitSchedule` by the MAP fit of
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
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import (ArgumentTypeError, DimensionError, NonFiniteError, OptionError,
                      ThetahatError, ThetahatWarning)
from ...model.system import PerturbedLinearSystem
from .ekf import (EKFKernels, JointEKF, as_record, ekf_kernels, resolve_noise_std,
                  sample_interval, start_values)
from .input_hold import InputHistory, smooth_input
from .stage2_set import stage2_set
from .fit_worker import default_executor, discard_default_executor, fit_spec, run_fit, warm_up
from .guard import (GUARD_C, GUARD_DWELL, GUARD_KAPPA, GUARD_RHO_MAX, make_guarded_loop,
                    progress_init)
from .mle import FitResult, FitSchedule, MapEstimator, fit_as_prior, fit_record
from .plant_kernel import H_RHO, jit
from .noise_level import MIN_SAMPLES
from ..protocol import Diagnostics, EstimateResult, missing_samples, phi_hat_from_model

__all__ = ["GuardedDiagnostics", "GuardedEstimator", "GuardedResult", "GuardedState",
           "StreamDiagnostics", "SIGMA_SAMPLES"]

FloatArray = NDArray[np.float64]

#: Samples after which σ̂ is re-estimated once before the first fit (when σ is not given).
SIGMA_SAMPLES = 32


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
        (:attr:`FitResult.consistent`), the others are counted by :attr:`fits_rejected`.
    fit_samples : ndarray of int
        The last sample of each fit's window (where a consistent one was applied).
    noise_std : ndarray (r,)
        The last σ used.
    failures : tuple of str
        Fits that raised or came back non-finite, one sentence each (ignored, with a
        ThetahatWarning: stage 1 and the EKF go on).
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

    @property
    def fits_rejected(self) -> int:
        """Fits that came back but failed their consistency checks (not applied)."""
        return sum(1 for f in self.fits if not f.consistent)

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
                f"noise_std={self.noise_std})")


#: The guarded estimator's former result name, kept importable (``thetahat.GuardedResult``):
#: :meth:`GuardedEstimator.run` returns an
#: :class:`~thetahat.estimation.protocol.EstimateResult` with :class:`GuardedDiagnostics`.
GuardedResult = EstimateResult


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
    stream : object or None
        The stream's shared data log, stage 2's (s, P) and pending fit (None before the first
        ``step``): states of one stream share it, so step each state once, in order.
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
    """

    stage1: Any
    x_hat0: FloatArray
    theta_hat0: FloatArray
    stream: Any = None
    theta_hat: FloatArray | None = None
    x_hat: FloatArray | None = None
    theta_stage1: FloatArray | None = None
    theta_stage2: FloatArray | None = None
    band: FloatArray | None = None
    clipped: bool = False
    reset: bool = False
    fits: int = 0
    fits_failed: int = 0

    def __repr__(self) -> str:
        return (f"GuardedState(theta_hat={self.theta_hat}, clipped={self.clipped}, "
                f"reset={self.reset}, fits={self.fits})")


@dataclass(frozen=True, slots=True, eq=False)
class StreamDiagnostics:
    """The fits of a streaming run so far (:meth:`GuardedEstimator.stream_diagnostics`).

    Attributes
    ----------
    fits : tuple of FitResult
        The fits that came back finite, in order (applied to stage 2 when consistent).
    fit_samples : ndarray of int, shape (n_fits, 2)
        Per fit: the last sample of its window and the sample whose ``step`` applied it (the
        first ``step`` after the fit finished).
    fit_seconds : ndarray, shape (n_fits,)
        Wall time of each fit in the worker (s).
    failures : tuple of str
        Fits that crashed or returned non-finite values, ignored (one warning each).
    pending : bool
        A fit is running (a finished one is applied by the next ``step``).
    """

    fits: tuple[FitResult, ...]
    fit_samples: NDArray[np.int64]
    fit_seconds: FloatArray
    failures: tuple[str, ...]
    pending: bool

    def __repr__(self) -> str:
        return (f"StreamDiagnostics(fits={len(self.fits)}, failures={len(self.failures)}, "
                f"pending={self.pending})")


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
        :func:`~thetahat.estimation.statistical.ekf.x_prior_sd` of x̂(0).
    kappa, c, rho_max, dwell : float
        The guard's constants (see :mod:`~thetahat.estimation.statistical.guard`); ``dwell`` a fraction
        of the samples so far (default :data:`~thetahat.estimation.statistical.guard.GUARD_DWELL`).
    q_x : float
        Stage 2's process-noise variance per sample on x (default 0: the model is exact).
    h_rho : float
        RK4 sub-step bound (see :mod:`~thetahat.estimation.statistical.plant_kernel`).
    compiled : bool, optional
        numba kernels (default: when installed).
    fit_executor : concurrent.futures.Executor, optional
        Where streaming fits run (anything with ``submit(fn, *args) -> Future``); default
        the shared worker process of :func:`~thetahat.estimation.statistical.fit_worker.default_executor`.
        :meth:`run` always fits in the caller.

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
    noise_std: Any = None
    schedule: FitSchedule | None = field(default=None)
    use_fits: bool = True
    x_sd: Any = None
    kappa: float = GUARD_KAPPA
    c: float = GUARD_C
    rho_max: float = GUARD_RHO_MAX
    dwell: float = GUARD_DWELL
    q_x: float = 0.0
    h_rho: float = H_RHO
    compiled: bool | None = None
    fit_executor: Any = None

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
            return self.schedule
        return FitSchedule(system=self.model, x_sd=self.x_sd, noise_std=self.noise_std,
                           compiled=self.compiled)

    def _loop(self) -> Any:
        k = self.kernels
        loop = _LOOPS.get(k)
        if loop is None:
            compiled = k.model.compiled
            loop = _LOOPS[k] = make_guarded_loop(k.predict, k.update, k.project,
                                                 lambda fn: jit(fn, compiled))
        return loop

    def _ekf(self) -> JointEKF:
        return JointEKF(system=self.model, noise_std=self.noise_std, x_sd=self.x_sd,
                        compiled=self.compiled)

    @staticmethod
    def _fit_or_none(sched: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
                     k1: int, prev: FitResult | None, prior0: tuple[FloatArray, FloatArray],
                     final: bool | None, failures: list[str]) -> FitResult | None:
        """The fit due at k1 (``final`` None: a schedule with times), or None with the reason
        appended to ``failures`` and a warning when it raised or came back non-finite."""
        try:
            fit = (sched.fit(t, U, Y, k1, prev, prior0) if final is None
                   else fit_record(sched, t, U, Y, k1, prev, prior0, final=final))
        except (ThetahatError, ArithmeticError, np.linalg.LinAlgError) as exc:
            why = f"the fit of samples 0…{k1 - 1} raised {type(exc).__name__}: {exc}"
        else:
            if fit.finite:
                return fit
            why = f"the fit of samples {fit.k0}…{fit.k1 - 1} came back non-finite"
        failures.append(why)
        warnings.warn(f"GuardedEstimator.run: a stage-2 fit was ignored: {why}. Stage 1 and "
                      "the EKF go on.", ThetahatWarning, stacklevel=3)
        return None

    def init(self, x_hat0: Any = None, theta_hat0: Any = None) -> GuardedState:
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
    def run(self, t: Any, u: Any, y: Any, *, state0: GuardedState | None = None
            ) -> EstimateResult:
        """Run both stages and the guard over a record.

        Parameters
        ----------
        t : array_like (N,)
        u : array_like (N, m) or (N,)
        y : array_like (N, r) or (N,)
        state0 : GuardedState, optional
            From :meth:`init` (default ``init()``); a record starts a new experiment, so a
            state that has been stepped is refused.

        Returns
        -------
        EstimateResult
            ``theta_hat`` the guarded output, ``x_hat`` stage 2's; ``diagnostics`` a
            :class:`GuardedDiagnostics` (both stages, the guard's band, the fits).

        Raises
        ------
        OptionError
            ``state0`` has been stepped (continue that stream with :meth:`step`).
        """
        sys_ = self.model
        n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
        t_, U, Y = as_record(t, u, y, m, r)
        # writable C copies: the compiled kernels' specialisation that streaming uses too
        U, Y = np.array(U, order="C"), np.array(Y, order="C")
        st0 = self.init() if state0 is None else state0
        if st0.stream is not None:
            raise OptionError("GuardedEstimator.run starts an experiment from init(); this "
                              "state0 has been stepped: continue its stream with step.")
        res1 = self.stage1.run(t_, U, Y, state0=st0.stage1)
        Us = np.array(smooth_input(U)[0], order="C")    # stage 2's input samples ũ
        xs = res1.x_hat if res1.x_hat_refined is None else res1.x_hat_refined
        # writable C copies (the compiled loop's array type)
        thG = np.array(res1.theta_hat, dtype=np.float64, order="C")
        xG = np.array(xs, dtype=np.float64, order="C")
        N = t_.shape[0]
        estimate_sigma = self.noise_std is None
        k_first = MIN_SAMPLES if estimate_sigma else 0
        sigma = resolve_noise_std(self.noise_std, Y[:max(k_first, MIN_SAMPLES)])
        R = np.diag(sigma ** 2)
        s, P0 = self._ekf().prior(st0.x_hat0, st0.theta_hat0)
        P = P0.copy()
        ts = stage2_set(sys_.require_parameter_set("stage 2"))
        lo, hi, ell = ts.lo, ts.hi, ts.ell
        out = {name: np.empty((N, w)) for name, w in
               (("TH", p), ("TH2", p), ("X2", n), ("SD2", p), ("BAND", p))}
        CLIP, RESET, NIS = np.zeros(N, bool), np.zeros(N, bool), np.full(N, np.nan)
        pst = progress_init(thG[0])
        gst = np.array([0.0, 1.0, float(k_first)])
        # (κ, c, ρ_max, dwell, σ₂ cap; θ_F, κ s_F of the latest consistent fit: none yet)
        cfg = np.concatenate([[self.kappa, self.c, self.rho_max, self.dwell],
                              np.sqrt(np.diag(P0)[n:]), np.zeros(p), np.full(p, -1.0)])
        loop = self._loop()
        sched = self.fit_schedule
        fits: list[FitResult] = []
        fit_at: list[int] = []
        failures: list[str] = []
        prior0 = (sched.initial_prior(st0.x_hat0, st0.theta_hat0) if sched else None)
        Q_x = self.q_x * np.eye(n)
        # the default fits: all the data so far, at the sample counts where the information
        # has grown by INFO_GROWTH, the last on all samples but the last (whose output then
        # follows it); a schedule with times keeps its times (seconds) and windows
        by_samples = sched is not None and sched.times is None
        ks: list[int] = []
        if sched is not None and by_samples:
            sched = replace(sched, full_window=math.inf)
            ks = [k1 for k1 in MapEstimator(system=sys_, schedule=sched, noise_std=self.noise_std,
                                            compiled=self.compiled).fit_samples(t_[:N - 1])
                  if MIN_SAMPLES <= k1 < N]
        k = 0
        j = 0
        while k < N:
            k_next = N
            if estimate_sigma:                  # σ̂ from MIN_SAMPLES, refined at 32
                if k in (MIN_SAMPLES, SIGMA_SAMPLES):
                    sigma = resolve_noise_std(None, Y[:k])
                    R = np.diag(sigma ** 2)
                if k < SIGMA_SAMPLES:
                    k_next = MIN_SAMPLES if k < MIN_SAMPLES else SIGMA_SAMPLES
            k_fit = N
            if sched is not None and by_samples:
                while j < len(ks) and ks[j] <= k:
                    j += 1
                k_fit = ks[j] if j < len(ks) else N
            elif sched is not None and sched.times is not None:
                while sched.times(j) <= t_[k] - t_[0]:
                    j += 1
                k_fit = int(np.searchsorted(t_ - t_[0], sched.times(j) + 1e-12, side="right"))
            k_next = min(k_fit, N, k_next)
            loop(s, P, P0, Us, Y, t_, k, k_next, 0, R, lo, hi, ell, self.h_rho, Q_x, thG, xG,
                 pst, gst, cfg, out["TH"], out["TH2"], out["X2"], out["SD2"], out["BAND"],
                 CLIP, RESET, NIS)
            due = sched is not None and k_next == k_fit < N
            # (due implies sched and prior0 are set; the two tests are spelled out for mypy)
            if sched is not None and prior0 is not None and due and MIN_SAMPLES <= k_next:
                prev = fits[-1] if fits else None
                fit = self._fit_or_none(sched, t_, Us, Y, k_next, prev, prior0,
                                        k_next == ks[-1] if by_samples else None, failures)
                if fit is not None:
                    fits.append(fit)
                    fit_at.append(k_next - 1)
                if fit is not None and fit.consistent:
                    # the fit ends at this very sample: take (x, θ) and their joint covariance
                    # stage 2 carries the model error as the fit found it (none: q = 0)
                    s_fit, P_fit, R, Q_x = fit_as_prior(sys_, fit, sample_interval(t_[:k_next]),
                                                        self.q_x)
                    s[:], P[:, :] = s_fit, P_fit
                    cfg[4 + p:4 + 2 * p] = fit.theta
                    cfg[4 + 2 * p:] = self.kappa * fit.theta_se
                    sigma = fit.noise_std
            if due and not by_samples:
                j += 1
            k = k_next
        if not np.all(np.isfinite(out["TH"])):
            raise NonFiniteError("the guarded output became non-finite: stage 1 diverged "
                                 "(check its gains and the data scaling).")
        diag = GuardedDiagnostics(theta_stage1=thG, theta_stage2=out["TH2"], theta_sd=out["SD2"],
                                  band=out["BAND"], clipped=CLIP, reset=RESET, nis=NIS,
                                  fits=tuple(fits),
                                  fit_samples=np.array(fit_at, dtype=np.int64), noise_std=sigma,
                                  failures=tuple(failures))
        return EstimateResult(t=t_, x_hat=out["X2"], theta_hat=out["TH"],
                              phi_hat=phi_hat_from_model(sys_, U, Y, out["X2"], out["TH"]),
                              skipped=missing_samples(Y), diagnostics=diag)

    # ------------------------------------------------------------------ streaming
    def step(self, state: GuardedState, u: Any, y: Any, dt: float) -> GuardedState:
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
            :meth:`stream_diagnostics`).
        """
        sys_ = self.model
        n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
        # own, writable copies (a read-only view would need its own compiled specialisation)
        u_ = np.zeros(0) if u is None else np.array(u, dtype=np.float64).reshape(m)
        y_ = np.array(y, dtype=np.float64).reshape(r)
        h = float(dt)
        if not h > 0 or not np.isfinite(h):
            raise DimensionError(f"dt must be finite and > 0; got {dt!r}.")
        if not np.all(np.isfinite(u_)):
            raise NonFiniteError("u contains NaN or inf; clean the input sample.")
        sh = state.stream or _Stream.start(self, state)
        k = sh.k
        est1 = self.stage1.estimate(state.stage1, u_, y_)
        thG = np.asarray(est1.theta_hat, dtype=np.float64).reshape(1, p)
        xs = est1.x_hat_refined if est1.x_hat_refined is not None else est1.x_hat
        xG = np.asarray(xs, dtype=np.float64).reshape(1, n)
        if k == 0:
            sh.configure(self, h)
        ut, sh.u_history = smooth_input(u_.reshape(1, m), sh.u_history)   # stage 2's ũ
        sh.record(k, ut[0], y_, h)
        sh.poll_fit()
        k0 = 0 if k == 0 else 1
        U2 = np.vstack([sh.u_prev, ut]) if k else ut.copy()
        Y2 = np.vstack([np.full(r, np.nan), y_]) if k else y_.reshape(1, r)
        tt = np.array([0.0, sh.dt_prev]) if k else np.zeros(1)
        TH2 = np.broadcast_to(thG, (2, p)).copy() if k else thG.copy()
        XG2 = np.broadcast_to(xG, (2, n)).copy() if k else xG.copy()
        rows = k0 + 1
        o = {name: np.zeros((rows, w)) for name, w in
             (("TH", p), ("TH2", p), ("X2", n), ("SD2", p), ("BAND", p))}
        clip, rst, nis = np.zeros(rows, bool), np.zeros(rows, bool), np.zeros(rows)
        if k == 0:
            sh.pst = progress_init(thG[0])
        self._loop()(sh.s, sh.P, sh.P0, U2, Y2, tt, k0, k0 + 1, k - k0, sh.R, sh.lo, sh.hi,
                     sh.ell, self.h_rho, sh.Q_x, TH2, XG2, sh.pst, sh.gst, sh.cfg, o["TH"],
                     o["TH2"], o["X2"], o["SD2"], o["BAND"], clip, rst, nis)
        s1 = self.stage1.step(state.stage1, u_, y_, h)
        sh.refresh_sigma(k)
        sh.u_prev, sh.dt_prev, sh.k = ut[0], h, k + 1
        sh.maybe_submit()
        return GuardedState(stage1=s1, x_hat0=state.x_hat0, theta_hat0=state.theta_hat0,
                            stream=sh, theta_hat=o["TH"][k0].copy(), x_hat=o["X2"][k0].copy(),
                            theta_stage1=thG[0].copy(), theta_stage2=o["TH2"][k0].copy(),
                            band=o["BAND"][k0].copy(), clipped=bool(clip[k0]),
                            reset=bool(rst[k0]), fits=len(sh.fits),
                            fits_failed=len(sh.failures))

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
        return StreamDiagnostics(fits=tuple(sh.fits),
                                 fit_samples=np.array(sh.fit_samples, np.int64).reshape(-1, 2),
                                 fit_seconds=np.array(sh.fit_seconds), failures=tuple(sh.failures),
                                 pending=sh.future is not None and not sh.future.done())

    def __repr__(self) -> str:
        return (f"GuardedEstimator(stage1={type(self.stage1).__name__}, n={self.model.n}, "
                f"p={self.model.p}, fits={'on' if self.use_fits else 'off'})")


_LOOPS: dict[Any, Any] = {}

#: Initial capacity (samples) of a stream's data log; it doubles when full.
_LOG_CAPACITY = 1024


class _Stream:
    """The data log, stage 2's (s, P) and the pending fit of one streaming run."""

    def __init__(self, est: GuardedEstimator, state: GuardedState) -> None:
        sys_ = est.model
        n = sys_.n
        self.k = 0
        self.s, self.P0 = est._ekf().prior(state.x_hat0, state.theta_hat0)
        self.P = self.P0.copy()
        self.Q_x = est.q_x * np.eye(n)
        ts = stage2_set(sys_.require_parameter_set("stage 2"))
        self.lo, self.hi, self.ell = ts.lo, ts.hi, ts.ell
        given = est.noise_std is not None
        self.R = (np.diag(resolve_noise_std(est.noise_std, np.zeros((1, sys_.r))) ** 2)
                  if given else np.eye(sys_.r))
        self.gst = np.array([0.0, 1.0, 0.0 if given else float(MIN_SAMPLES)])
        self.cfg = np.array([])
        self.pst = np.zeros((sys_.p, 6))
        self.u_prev = np.zeros(sys_.m)
        self.u_history: InputHistory | None = None
        self.dt_prev = 0.0
        # the samples since the start of the current fit window: sample i is the stream's
        # sample base + i (a log in arrays, so that a fit's window is one copy at submission)
        self.T: FloatArray = np.empty(_LOG_CAPACITY)
        self.U: FloatArray = np.empty((_LOG_CAPACITY, sys_.m))
        self.Y: FloatArray = np.empty((_LOG_CAPACITY, sys_.r))
        self.size = 0
        self.base = 0
        self.fits: list[FitResult] = []
        self.fit_samples: list[tuple[int, int]] = []
        self.fit_seconds: list[float] = []
        self.failures: list[str] = []
        self.future: concurrent.futures.Future[Any] | None = None
        self.j = 0
        self.sched = est.fit_schedule
        self.prior0 = (self.sched.initial_prior(state.x_hat0, state.theta_hat0)
                       if self.sched else None)
        self.executor: concurrent.futures.Executor | None = None
        self.spec = b""
        self._n = n

    @classmethod
    def start(cls, est: GuardedEstimator, state: GuardedState) -> _Stream:
        """A new stream; with fits, the worker starts compiling the fit kernels at once (the
        first fit queues behind that warm-up; its errors, if any, come back with the fit)."""
        sh = cls(est, state)
        if sh.sched is not None:
            sh.executor = (est.fit_executor if est.fit_executor is not None
                           else default_executor())
            sh.spec = fit_spec(sh.sched)
            sh.submit(warm_up, sh.spec)
            sh.future = None
        return sh

    def record(self, k: int, u: FloatArray, y: FloatArray, dt: float) -> None:
        i = self.size
        if i == self.T.shape[0]:
            self._resize(2 * i)
        self.T[i] = 0.0 if k == 0 else self.T[i - 1] + self.dt_prev
        self.U[i] = u
        self.Y[i] = y
        self.size = i + 1

    def _resize(self, capacity: int, cut: int = 0) -> None:
        """New log arrays of ``capacity`` holding samples cut … size − 1 (never written in
        place: a window handed to the executor stays intact)."""
        keep = self.size - cut
        T, U, Y = (np.empty((capacity,) + a.shape[1:]) for a in (self.T, self.U, self.Y))
        T[:keep], U[:keep], Y[:keep] = self.T[cut:self.size], self.U[cut:self.size], \
            self.Y[cut:self.size]
        self.T, self.U, self.Y, self.size = T, U, Y, keep

    def refresh_sigma(self, k: int) -> None:
        """σ̂ from the samples so far, after sample k = MIN_SAMPLES − 1 and SIGMA_SAMPLES − 1
        (as :meth:`GuardedEstimator.run` does), when σ is estimated."""
        if k + 1 in (MIN_SAMPLES, SIGMA_SAMPLES) and self.gst[2] > 0:
            self.R = np.diag(resolve_noise_std(None, self.Y[:self.size]) ** 2)

    def configure(self, est: GuardedEstimator, dt: float) -> None:
        n = self._n
        p = self.P0.shape[0] - n
        self.cfg = np.concatenate([[est.kappa, est.c, est.rho_max, est.dwell],
                                   np.sqrt(np.diag(self.P0)[n:]), np.zeros(p), np.full(p, -1.0)])

    def submit(self, fn: Any, *args: Any) -> None:
        """Hand ``fn(*args)`` to the executor; a broken executor ends this stream's fits."""
        if self.executor is None:               # (start sets it whenever fits run)
            return
        try:
            self.future = self.executor.submit(fn, *args)
        except (concurrent.futures.BrokenExecutor, RuntimeError) as exc:
            self._broken(exc)

    def _broken(self, exc: BaseException) -> None:
        self._reject(f"the fit worker failed ({type(exc).__name__}: {exc}); no more fits in "
                     "this stream (a script that streams must keep its top-level code under "
                     "`if __name__ == \"__main__\":` for the worker process to start)")
        if self.executor is not None:
            discard_default_executor(self.executor)
        self.sched = None
        self.future = None

    def _reject(self, why: str) -> None:
        self.failures.append(why)
        warnings.warn(f"GuardedEstimator.step: a stage-2 fit was ignored: {why}. Stage 1 and "
                      "the EKF go on.", ThetahatWarning, stacklevel=4)

    def poll_fit(self) -> None:
        """Apply a finished fit (at the first step after it finished); never waits."""
        f = self.future
        if f is None or not f.done():
            return
        self.future = None
        try:
            done = f.result()
        except concurrent.futures.BrokenExecutor as exc:
            self._broken(exc)
            return
        except Exception as exc:                # a crashed fit is ignored, with a diagnostic
            self._reject(f"it raised {type(exc).__name__}: {exc}")
            return
        fit = done.fit
        if not fit.finite:
            self._reject(f"non-finite result on samples {fit.k0}…{fit.k1 - 1}")
            return
        n = self._n
        self.fits.append(fit)
        self.fit_samples.append((fit.k1 - 1, self.k))
        self.fit_seconds.append(done.seconds)
        if fit.consistent:                      # θ only: x has moved on since the fit
            self.s[n:] = fit.theta
            self.P[n:, :] = 0.0
            self.P[:, n:] = 0.0
            self.P[n:, n:] = fit.cov[n:, n:]
            self.R = np.diag(fit.noise_std ** 2)
            p = fit.theta.shape[0]
            self.cfg[4 + p:4 + 2 * p] = fit.theta
            self.cfg[4 + 2 * p:] = self.cfg[0] * fit.theta_se
        if fit.k0 > 0 or (self.sched is not None and self.T[fit.k1 - 1 - self.base]
                          > self.sched.full_window):
            self._trim(fit.k1 - 1)

    def _trim(self, new_base: int) -> None:
        cut = new_base - self.base
        if cut > 0:
            self._resize(self.T.shape[0], cut)
            self.base = new_base

    def maybe_submit(self) -> None:
        sched, prior0 = self.sched, self.prior0       # prior0 is None exactly when sched is
        if sched is None or prior0 is None or self.future is not None:
            return
        t_last = float(self.T[self.size - 1])
        if self.k < MIN_SAMPLES:
            return
        if sched.times is None:                 # sample counts: the data so far, k_j of them
            at = sched.sample_counts()
            if self.k < at(self.j):
                return
            while at(self.j) <= self.k:
                self.j += 1
        else:                                   # the caller's times (s)
            if t_last < sched.times(self.j) - 1e-12:
                return
            while sched.times(self.j) <= t_last + 1e-12:
                self.j += 1
        b, k1 = self.base, self.size
        prev = self.fits[-1] if self.fits else None
        if prev is not None:
            prev = dataclasses.replace(prev, k0=max(prev.k0 - b, 0), k1=prev.k1 - b)
        self.submit(run_fit, self.spec, self.T[:k1].copy(), self.U[:k1].copy(),
                    self.Y[:k1].copy(), k1, prev, prior0, t_last, b, sched.times is None)
