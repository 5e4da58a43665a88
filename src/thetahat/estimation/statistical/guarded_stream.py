"""The guarded estimator's stream: its data log, stage 2's (s, P) and the pending fit.

A streaming :meth:`~thetahat.estimation.statistical.guarded.GuardedEstimator.step` keeps one
:class:`GuardedStream`, shared by the states of that stream: the samples since the current
fit window began (arrays that double when full, so that a fit's window is one copy at
submission), stage 2's state and covariance, σ (refreshed as the guarded ``run`` refreshes
it), the guard's constants, and the fit handed to the worker of
:mod:`~thetahat.estimation.statistical.fit_worker` (applied at the first ``step`` after it
finished: a ``step`` never waits for a fit). A fit that crashes or comes back non-finite is
ignored with a :class:`~thetahat.errors.ThetahatWarning`; :class:`StreamDiagnostics` counts
the fits.

With a ``window`` W (:mod:`~thetahat.estimation.statistical.window`; ``"auto"`` decided on the
samples so far at the counts where :meth:`GuardedEstimator.run` would decide it on the record)
the fits past W samples are those of the log's samples since the previous fit, every W
samples, with the posterior at the window's first sample as arrival cost: that of the
previous fit, which ended there, when it was applied (as ``run`` re-anchors on it), else
stage 2's when that fit was handed over; the log is emptied to that sample at each
hand-over. It then holds at most W + 1 samples, plus those stepped while a fit is still
running: memory and each fit's work no longer grow with the stream.

What it may import: the package's errors, and, in this room, ``common``, ``fit_worker``,
``input_hold``, ``map_fit``, ``noise_level``, ``plant_kernel``, ``stage2_set`` and ``window``;
never the
guarded estimator
(which builds the stream from plain values).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...errors import ThetahatWarning
from ...model.system import PerturbedLinearSystem
from ..hold import DEFAULT_HOLD
from .common import resolve_noise_std, sample_interval
from .fit_worker import default_executor, discard_default_executor, fit_spec, run_fit, warm_up
from .guard import apply_fit
from .input_hold import InputHistory
from .map_fit import FitResult, FitSchedule, fit_as_prior, why_not_applied
from .noise_level import MIN_SAMPLES
from .plant_kernel import H_RHO, Propagation
from .stage2_set import stage2_set
from .window import WINDOW_MAX, stream_window, window_grid, windowed_counts

__all__ = ["GuardedStream", "LOG_CAPACITY", "SIGMA_SAMPLES", "StreamDiagnostics"]

FloatArray = NDArray[np.float64]

#: Samples after which σ̂ is re-estimated once before the first fit (when σ is not given).
SIGMA_SAMPLES = 32

#: Initial capacity (samples) of a stream's data log; it doubles when full.
LOG_CAPACITY = 1024


@dataclass(frozen=True, slots=True, eq=False)
class StreamDiagnostics:
    """The fits of a streaming run so far (``GuardedEstimator.stream_diagnostics``).

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
    rejected : tuple of str
        The fits that came back but were not applied (not consistent with the noise, or
        :meth:`~.map_fit.FitResult.rejection`), one sentence each.
    stage1_failed_at : int or None
        The sample from which stage 1 is lost (its step or estimate raised there), None while
        it runs; as ``GuardedDiagnostics.stage1_failed_at`` of a run.
    stage1_message : str
        Stage 1's error then ("" otherwise).
    window : int or None
        The stream's window W once decided (None: not yet, or fits of all the data).
    stage1_backend : str
        What steps stage 1 at the stream's first ``dt``: the class of the back end
        (``"NativeObserver"``, the C printed from the formulas; ``"CompiledObserver"``,
        numba's kernel) or of stage 1 itself (``"ModifiedHighGainObserver"``: its NumPy step).
    """

    fits: tuple[FitResult, ...]
    fit_samples: NDArray[np.int64]
    fit_seconds: FloatArray
    failures: tuple[str, ...]
    pending: bool
    rejected: tuple[str, ...] = ()
    stage1_failed_at: int | None = None
    stage1_message: str = ""
    window: int | None = None
    stage1_backend: str = ""

    @property
    def fits_rejected(self) -> int:
        """Fits that came back but were not applied."""
        return len(self.rejected)

    def __repr__(self) -> str:
        return (f"StreamDiagnostics(fits={len(self.fits)}, failures={len(self.failures)}, "
                + ("" if self.stage1_failed_at is None
                   else f"stage1_failed_at={self.stage1_failed_at}, ")
                + ("" if self.window is None else f"window={self.window}, ")
                + f"pending={self.pending})")


class GuardedStream:
    """The data log, stage 2's (s, P) and the pending fit of one streaming run.

    Parameters
    ----------
    system : PerturbedLinearSystem
        Stage 2's model.
    s0, P0 : ndarray (n + p,), (n + p, n + p)
        Stage 2's prior (:func:`~thetahat.estimation.statistical.common.joint_prior`).
    q_x : float
        Stage 2's process-noise variance per sample on x.
    noise_std : float or array_like (r,), optional
        σ; None: estimated from the first samples.
    schedule : FitSchedule or None
        The fits (None: no fits).
    prior0 : (ndarray, ndarray) or None
        The first fit's prior (:meth:`~.map_fit.FitSchedule.initial_prior`; None without fits).
    hold : str
        Stage 2's hold (not ``"bandlimited"``: a stream has no later samples).
    h_rho : float
        The RK4 sub-steps' stability bound.
    substeps : int, optional
        The RK4 sub-steps' accuracy floor without fits (default 1; with fits each fit sets
        it, starting from the schedule's).
    window : {None, "auto"} or int
        The fits' window (module docstring; checked by the estimator); not with a schedule
        with ``times``.
    window_max : int
        The longest ``"auto"`` window.
    """

    def __init__(self, system: PerturbedLinearSystem, s0: FloatArray, P0: FloatArray, *,
                 q_x: float, noise_std: ArrayLike | None, schedule: FitSchedule | None,
                 prior0: tuple[FloatArray, FloatArray] | None, hold: str = DEFAULT_HOLD,
                 h_rho: float = H_RHO, substeps: int | None = None,
                 window: int | str | None = None, window_max: int = WINDOW_MAX) -> None:
        sys_ = system
        n = sys_.n
        self.owner: Any = None              # the estimator that started the stream
        self.loop: Any = None               # its guarded loop (looked up once, not per step)
        self.read_stage1: Any = None        # its stage 1's (x̂, θ̂, x̂₂) reader (likewise)
        self.step_stage1: Any = None        # its stage 1's read and step in one call
        self.stage1_backend = ""            # and the name of what steps it
        self.last: Any = None               # the state the last step returned
        self.k = 0
        self.s, self.P0 = s0, P0
        self.P = self.P0.copy()
        self.system, self.q_x = sys_, q_x
        self.Q_x = q_x * np.eye(n)
        ts = stage2_set(sys_.require_parameter_set("stage 2"))
        self.lo, self.hi, self.ell = ts.lo, ts.hi, ts.ell
        given = noise_std is not None
        self.R = (np.diag(resolve_noise_std(noise_std, np.zeros((1, sys_.r))) ** 2)
                  if given else np.eye(sys_.r))
        self.gst = np.array([0.0, 1.0, 0.0 if given else float(MIN_SAMPLES)])
        self.cfg = np.array([])
        self.pst = np.zeros((sys_.p, 6))
        self.hold = hold
        floor = substeps if schedule is None else schedule.substeps
        self.pc, self.WT = Propagation(hold=hold, substeps=floor or 1, h_rho=h_rho).arrays()
        self.u_prev = np.zeros(sys_.m)
        self.u_history: InputHistory | None = None
        self.dt_prev = 0.0
        # the samples since the start of the current fit window: sample i is the stream's
        # sample base + i (a log in arrays, so that a fit's window is one copy at submission)
        self.T: FloatArray = np.empty(LOG_CAPACITY)
        self.U: FloatArray = np.empty((LOG_CAPACITY, sys_.m))
        self.Y: FloatArray = np.empty((LOG_CAPACITY, sys_.r))
        self.size = 0
        self.base = 0
        self.fits: list[FitResult] = []
        self.applied: FitResult | None = None
        self.rejected: list[str] = []
        self.fit_samples: list[tuple[int, int]] = []
        self.fit_seconds: list[float] = []
        self.failures: list[str] = []
        self.future: concurrent.futures.Future[Any] | None = None
        self.j = 0
        self.sched = schedule
        self.prior0 = prior0 if schedule else None
        # the window: W once decided (an integer at once; "auto" at the grid's counts), the
        # fit counts (j ↦ k_j, windowed once W is known), and the arrival cost (s, P, σ) of
        # the next window fit at the log's first sample
        self.window, self.window_max = window, window_max
        self.W: int | None = (int(window) if window is not None and window != "auto"
                              else None)
        self.grid = (frozenset(window_grid(system, window_max))
                     if window == "auto" else frozenset())
        self.at: Any = None
        self.anchor: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self.executor: concurrent.futures.Executor | None = None
        self.stage1_failed_at: int | None = None     # stage 1 lost from this sample on
        self.stage1_message = ""
        self.spec = b""
        self._n = n
        # the guarded loop's arrays for one step, allocated once: in, two rows (the previous
        # sample, held, and this one; the first step uses row 0 only) of u, y, t, θ̂_G, x̂_G;
        # out, the loop's rows of θ̂, θ̂₂, x̂₂, sd₂, band, clipped, reset, NIS
        m, r, p = sys_.m, sys_.r, sys_.p
        self.step_in = (np.zeros((2, m)), np.full((2, r), np.nan), np.zeros(2),
                        np.zeros((2, p)), np.zeros((2, n)))
        self.step_out = (np.zeros((2, p)), np.zeros((2, p)), np.zeros((2, n)),
                         np.zeros((2, p)), np.zeros((2, p)), np.zeros(2, bool),
                         np.zeros(2, bool), np.zeros(2))

    @classmethod
    def start(cls, system: PerturbedLinearSystem, s0: FloatArray, P0: FloatArray, *,
              q_x: float, noise_std: ArrayLike | None, schedule: FitSchedule | None,
              prior0: tuple[FloatArray, FloatArray] | None,
              executor: concurrent.futures.Executor | None, hold: str = DEFAULT_HOLD,
              h_rho: float = H_RHO, substeps: int | None = None,
              window: int | str | None = None, window_max: int = WINDOW_MAX
              ) -> GuardedStream:
        """A new stream; with fits, the worker starts compiling the fit kernels at once (the
        first fit queues behind that warm-up; its errors, if any, come back with the fit).

        Parameters
        ----------
        system, s0, P0, q_x, noise_std, schedule, prior0, hold, h_rho, substeps, window, window_max
            As the class's.
        executor : concurrent.futures.Executor, optional
            Where the fits run (default
            :func:`~thetahat.estimation.statistical.fit_worker.default_executor`).

        Returns
        -------
        GuardedStream
        """
        sh = cls(system, s0, P0, q_x=q_x, noise_std=noise_std, schedule=schedule,
                 prior0=prior0, hold=hold, h_rho=h_rho, substeps=substeps, window=window,
                 window_max=window_max)
        if sh.sched is not None:
            sh.executor = executor if executor is not None else default_executor()
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
        (as the guarded estimator's ``run`` does), when σ is estimated."""
        if k + 1 in (MIN_SAMPLES, SIGMA_SAMPLES) and self.gst[2] > 0:
            self.R = np.diag(resolve_noise_std(None, self.Y[:self.size]) ** 2)

    def configure(self, kappa: float, c: float, rho_max: float, dwell: float) -> None:
        """The guard's constants (κ, c, ρ_max, dwell, σ₂ cap; no fit yet) at the first step."""
        n = self._n
        p = self.P0.shape[0] - n
        self.cfg = np.concatenate([[kappa, c, rho_max, dwell],
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
        why = why_not_applied(fit, self.applied)
        if why is not None:
            self.rejected.append(why)
        else:                                   # θ only: x has moved on since the fit
            self.applied = fit
            self.pc, self.WT = Propagation(hold=self.hold, substeps=fit.substeps,
                                           h_rho=float(self.pc[0])).arrays()
            apply_fit(self.s, self.P, self.R, self.cfg, fit.theta, fit.cov[n:, n:],
                      np.asarray(fit.noise_std, dtype=np.float64))
            # stage 2 carries the model error as the fit found it (none: q = 0), as in run
            self.Q_x = fit_as_prior(self.system, fit, sample_interval(self.T[:self.size]),
                                    self.q_x)[3]
        if fit.k0 > 0 or (self.sched is not None and self.T[fit.k1 - 1 - self.base]
                          > self.sched.full_window):
            self._trim(fit.k1 - 1)

    def _trim(self, new_base: int) -> None:
        cut = new_base - self.base
        if cut > 0:
            self._resize(self.T.shape[0], cut)
            self.base = new_base

    def _decide_window(self, sched: FitSchedule, prior0: tuple[FloatArray, FloatArray]
                       ) -> None:
        """``"auto"``: W at this sample count if the samples so far decide it (the rule of
        :func:`~thetahat.estimation.statistical.window.resolve_window`, so that a stream's
        W is the run's on the same samples)."""
        self.W = stream_window(sched, self.T, self.U, self.Y, self.k, prior0, self.window_max,
                               self.grid)
        if self.W is not None:
            self.at = None                      # the counts become the windowed ones

    def maybe_submit(self) -> None:
        sched, prior0 = self.sched, self.prior0       # prior0 is None exactly when sched is
        if sched is None or prior0 is None:
            return
        if self.window == "auto" and self.W is None and sched.times is None:
            self._decide_window(sched, prior0)  # (at every count, a fit pending or not)
        if self.future is not None:
            return
        t_last = float(self.T[self.size - 1])
        if self.k < MIN_SAMPLES:
            return
        W = self.W
        if sched.times is None:                 # sample counts: the data so far, k_j of them
            if self.at is None:
                at = sched.sample_counts()
                self.at = at if W is None else windowed_counts(at, W)
            at = self.at
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
        window = self._arrival() if W is not None and self.k > W else None
        prev = self.fits[-1] if self.fits and window is None else None
        if prev is not None:
            prev = dataclasses.replace(prev, k0=max(prev.k0 - b, 0), k1=prev.k1 - b)
        self.submit(run_fit, self.spec, self.T[:k1].copy(), self.U[:k1].copy(),
                    self.Y[:k1].copy(), k1, prev, prior0, t_last, b, sched.times is None,
                    window)
        if W is not None and self.k >= W and self.future is not None:
            # the next window starts at this sample: stage 2's posterior here its arrival
            # cost, the log emptied to it (the fit just handed over has its own copy)
            self.anchor = (self.s.copy(), self.P.copy(), np.sqrt(np.diag(self.R)))
            self._trim(self.k - 1)

    def _arrival(self) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The arrival cost (s, P, σ) at the log's first sample: the posterior of the fit
        that ended there when it was applied (as :meth:`GuardedEstimator.run`, which
        re-anchors stage 2 on it), else stage 2's at the hand-over (None: no window yet)."""
        fit = self.applied
        if self.anchor is not None and fit is not None and fit.k1 - 1 == self.base:
            return (np.concatenate([fit.x_end, fit.theta]),
                    np.asarray(fit.cov_end, dtype=np.float64),
                    np.asarray(fit.noise_std, dtype=np.float64))
        return self.anchor

    def diagnostics(self) -> StreamDiagnostics:
        """The fits of this stream so far.

        Returns
        -------
        StreamDiagnostics
        """
        return StreamDiagnostics(fits=tuple(self.fits),
                                 fit_samples=np.array(self.fit_samples, np.int64).reshape(-1, 2),
                                 fit_seconds=np.array(self.fit_seconds),
                                 failures=tuple(self.failures),
                                 pending=self.future is not None and not self.future.done(),
                                 rejected=tuple(self.rejected),
                                 stage1_failed_at=self.stage1_failed_at,
                                 stage1_message=self.stage1_message, window=self.W,
                                 stage1_backend=self.stage1_backend)
