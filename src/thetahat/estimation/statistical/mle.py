"""The MAP estimator (method "mle"): MAP fits of all the data so far, the EKF between them.

:class:`MapEstimator` fits all the data so far (:mod:`~thetahat.estimation.statistical.map_fit`)
each time the information has grown by a factor (:func:`~.map_fit.information_schedule`:
counts of samples, never seconds), warm-started from the previous fit; its last fit is the MAP
estimate of the whole record. Between fits its estimate is the joint EKF started from the
latest fit's posterior (:func:`~.map_fit.fit_as_prior`: the fit is the arrival cost of the
samples before it), so every row, not only the fits', follows the information of the data so
far. With ``window`` (:mod:`~thetahat.estimation.statistical.window`) the fits past W samples
are of the W samples since the previous fit, that fit's posterior their arrival cost: each fit
O(W) and a stream's memory W + 1 samples, whatever the record's length. A window fit that
does not fit (:func:`~.map_fit.why_not_applied`: output-error fits of a record with model
error are inconsistent) is not applied; the EKF carries on, and its posterior is the next
window's arrival cost. A run stops where the
EKF between fits diverges or a fit fails
(:mod:`~thetahat.estimation.status`: raised with ``throw=True``, returned with ``throw=False``).

The input between the samples is the ``hold``'s (:mod:`~thetahat.estimation.hold`; default
``"smooth"``), and the RK4 sub-steps of a record are chosen once, at the start values
(:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`), for the fits and the
EKF between them alike (the final fit checks them at its estimate).

What it may import: :mod:`thetahat.model`, the package's errors, the bottom of the estimation
wing (``protocol``, ``records``, ``status``), and, in this room, ``common``, ``ekf_kernels``,
``input_hold``, ``map_fit``, ``noise_level``, ``plant_kernel``, ``stage2_set``, ``sweep`` and
``window``.
"""

from __future__ import annotations

import bisect
import math
import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...errors import NonFiniteError, OptionError, StateError, ThetahatWarning
from ...model.system import PerturbedLinearSystem
from ...progress import FitProgress
from ..protocol import (Diagnostics, EstimateResult, check_state, missing_samples,
                        stream_sample)
from ..records import check_record
from ..status import Status
from .common import (RunStop, model_phi_hat, resolve_noise_std, sample_interval, start_values,
                     stopped_result, theta_prior_sd)
from .ekf_kernels import divergence_message, ekf_kernels, ekf_sample
from ..hold import DEFAULT_HOLD, check_hold
from .input_hold import InputHistory, stage2_samples, streamable
from .map_fit import (INFO_GROWTH, FitResult, FitSchedule, fit_as_prior, fit_record,
                      why_not_applied)
from .noise_level import MIN_SAMPLES
from .plant_kernel import Propagation, choose_substeps, model_kernel
from .sweep import sweep_kernel
from .stage2_set import stage2_set
from .window import (WINDOW_MAX, check_window, fit_window, resolve_window,
                     stream_window, window_grid, windowed, windowed_counts)

__all__ = ["MapDiagnostics", "MapEstimator", "MapState", "fit_stop"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class MapDiagnostics(Diagnostics):
    """What :class:`MapEstimator` reports beyond the common estimates (``result.diagnostics``).

    Attributes
    ----------
    theta_sd : ndarray (N, p)
        The standard error of θ̂ (the prior's before the first fit).
    fits : tuple of FitResult
    fit_samples : ndarray of int
        The sample at which each fit's window ends.
    substeps : int
        The RK4 sub-steps' accuracy floor of the run.
    rejected : tuple of str
        The window fits that came back but were not applied, one sentence each
        (:func:`~.map_fit.why_not_applied`; the rows after them are the EKF's, carried on from
        the last fit applied). Fits of all the data are always applied.
    """

    theta_sd: FloatArray
    fits: tuple[FitResult, ...]
    fit_samples: NDArray[np.int64]
    substeps: int = 1
    rejected: tuple[str, ...] = ()

    @property
    def fit_cost(self) -> FloatArray:
        """Each fit's cost per measurement (≈ 1 when the model and σ are right)."""
        return np.array([f.cost for f in self.fits])

    def __repr__(self) -> str:
        return (f"MapDiagnostics(fits={len(self.fits)}, "
                f"fit_samples={self.fit_samples.tolist()[:8]}"
                f"{'…' if len(self.fits) > 8 else ''})")


class _MapLog:
    """The samples of one MAP stream (arrays that double when full; shared by its states).

    With a window the log is emptied to its last sample at each windowed fit (:meth:`trim`):
    it then holds at most W + 1 samples, sample ``offset + i`` at row i."""

    def __init__(self, m: int, r: int, owner: Any) -> None:
        self.owner = owner                  # the estimator that started the stream
        self.last: Any = None               # the state the stream's last step returned
        # what every step of the stream reads, looked up once: the owner's schedule, its
        # sample counts (by window), the prior of the start values, the stream's hold
        self.sched: Any = None
        self.counts: dict[int | None, Any] = {}
        self.prior0: Any = None
        self.hold = ""
        self.T: FloatArray = np.empty(256)
        self.U: FloatArray = np.empty((256, m))
        self.Y: FloatArray = np.empty((256, r))
        self.size = 0
        self.offset = 0

    def trim(self, k: int) -> None:
        """Keep samples k … (dropping the older ones)."""
        i = k - self.offset
        for a in (self.T, self.U, self.Y):
            a[:self.size - i] = a[i:self.size].copy()
        self.size -= i
        self.offset = k

    def append(self, t: float, u: FloatArray, y: FloatArray) -> None:
        i = self.size
        if i == self.T.shape[0]:
            self.T, self.U, self.Y = (np.concatenate([a, np.empty_like(a)])
                                      for a in (self.T, self.U, self.Y))
        self.T[i], self.U[i], self.Y[i] = t, u, y
        self.size = i + 1


@dataclass(frozen=True, slots=True, eq=False)
class MapState:
    """The state of :class:`MapEstimator`: the start values and, once streaming, the latest
    estimates and the stream's data log.

    Attributes
    ----------
    x_hat0, theta_hat0 : ndarray (n,), (p,)
        x̂(0) and θ̂(0) (θ̂(0) in Θ): the prior of the first fit.
    x_hat, theta_hat, theta_sd : ndarray (n,), (p,), (p,)
        The estimates at the last sample stepped: before the first fit θ̂(0) and x̂ predicted
        by the model, then the joint EKF continued from the latest fit (:func:`fit_as_prior`).
    k : int
        Samples stepped.
    elapsed : float
        Time of the last sample since the first.
    j : int
        The next scheduled fit.
    fits : tuple of FitResult
    fit_samples : tuple of int
        The sample at which each fit's window ends.
    dt_prev : float
        The last step's dt.
    log : object or None
        The stream's samples (None before the first ``step``), shared by its states; its
        inputs are stage 2's ũ (:func:`~thetahat.estimation.statistical.input_hold.smooth_input`).
    u_history : InputHistory or None
        The raw inputs the next samples' ũ need.
    P, R, Q_x : ndarray or None
        The EKF's covariance of col(x̂, θ̂), output-noise covariance and process noise on x
        since the latest fit (None before the first fit).
    substeps : int
        The RK4 sub-steps' accuracy floor of the latest fit applied (1 before).
    window : int or None
        The stream's window W once decided (None: not yet, or fits of all the data).
    anchor : tuple or None
        With a window: (k0, col(x̂, θ̂), P, σ) at the sample where the next window starts (the
        last fit applied's posterior, or the EKF's where a window fit was not applied).
    rejected : tuple of str
        The window fits not applied (:attr:`MapDiagnostics.rejected`).
    """

    x_hat0: FloatArray
    theta_hat0: FloatArray
    x_hat: FloatArray
    theta_hat: FloatArray
    theta_sd: FloatArray
    k: int = 0
    elapsed: float = 0.0
    j: int = 0
    fits: tuple[FitResult, ...] = ()
    fit_samples: tuple[int, ...] = ()
    dt_prev: float = 0.0
    log: _MapLog | None = None
    u_history: InputHistory | None = None
    P: FloatArray | None = None
    R: FloatArray | None = None
    Q_x: FloatArray | None = None
    substeps: int = 1
    window: int | None = None
    anchor: tuple[int, FloatArray, FloatArray, FloatArray] | None = None
    rejected: tuple[str, ...] = ()

    def __repr__(self) -> str:
        return (f"MapState(k={self.k}, theta_hat={self.theta_hat}, fits={len(self.fits)})")


@dataclass(frozen=True, slots=True)
class _Carry:
    """The EKF carried on from the last fit applied past window fits that were not: the next
    sample k, col(x̂, θ̂) and P at k − 1 (advanced in place), and the fit's R and Q_x."""

    k: int
    s: FloatArray
    P: FloatArray
    R: FloatArray
    Q_x: FloatArray


def _warn_rejected(where: str, rejected: list[str], total: int | None) -> None:
    """One warning for the window fits not applied (:attr:`MapDiagnostics.rejected`; a
    stream's, ``total`` None: at its first, the others in ``MapState.rejected``)."""
    count = (f"{len(rejected)} of {total} fits were not applied (the first: {rejected[0]})"
             if total is not None else f"a window fit was not applied ({rejected[0]}; this "
             "stream's later ones are listed in its state's rejected, not warned again)")
    warnings.warn(f"{where}: {count}. The window's fits are output-error fits of W samples; on "
                  "a record the model does not explain without process noise they are "
                  "inconsistent, and θ̂ after them is the EKF's, carried on from the last fit "
                  "applied. window=None fits all the data, with process noise where the "
                  "output-error fit is inconsistent.", ThetahatWarning, stacklevel=3)


@dataclass(frozen=True, slots=True, eq=False)
class MapEstimator:
    """Offline estimation by MAP fits alone on a schedule (method ``"mle"``).

    By default every fit is a fit of all the data so far (Gauss–Newton over (x(0), θ) with
    exact sensitivities, O(N) per iteration, warm-started from the previous fit), at the sample
    counts of :func:`~.map_fit.information_schedule` from
    :func:`~.map_fit.first_fit_samples`, and the last fit takes the whole record: θ̂ at the
    end is the MAP estimate of the record, with no block approximation, at any record length
    and sampling rate. Between fits the joint EKF runs
    from the latest fit (:func:`fit_as_prior`), so the rows between fits are not the stale fit.

    Parameters
    ----------
    system : PerturbedLinearSystem
    schedule : FitSchedule, optional
        The fits' settings; with ``times`` given, fit at those times (seconds) and windows
        instead (block fits with arrival cost).
    noise_std : optional
        σ of the output noise; default estimated from the data of each fit.
    compiled : bool, optional
    growth : float
        Information growth between fits of the default schedule (default √2).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`; ``"bandlimited"`` for
        :meth:`run` only).
    substeps : int, optional
        The RK4 sub-steps' accuracy floor; default: chosen per record (module docstring; in
        :meth:`step`, by each fit on its window).
    window : {None, "auto"} or int
        None (default): every fit is of all the data so far. An integer W, or ``"auto"``
        (W from the information the data carry,
        :mod:`~thetahat.estimation.statistical.window`): bounded fits — once the record
        passes W samples, a fit every W samples of the samples since the previous fit, with
        that fit's posterior (the EKF's at the window's start) as the arrival cost; each
        fit's cost and a stream's memory are then O(W) whatever the record's length. A
        window fit that does not fit is not applied (:attr:`MapDiagnostics.rejected`, one
        warning): the EKF carries on from the last fit applied. Not with a ``schedule``
        that has ``times``.
    window_max : int
        The longest ``"auto"`` window (default
        :data:`~thetahat.estimation.statistical.window.WINDOW_MAX` samples).

    Notes
    -----
    An :class:`~thetahat.estimation.protocol.Estimator`: :meth:`init` gives a
    :class:`MapState`; :meth:`step` appends one sample and runs the fits whose window ends
    there (in the caller); :meth:`run` fits a record; results carry :class:`MapDiagnostics`.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.mle import MapEstimator
    >>> data = lugre.simulate(seed=0, t_end=0.2)
    >>> est = MapEstimator(system=lugre.system(), compiled=False)
    >>> res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    >>> bool(abs(res.theta_hat[-1, 0] - 0.28) < 0.01)
    True
    """

    system: PerturbedLinearSystem
    schedule: FitSchedule | None = None
    noise_std: ArrayLike | None = None
    compiled: bool | None = None
    growth: float = INFO_GROWTH
    hold: str = DEFAULT_HOLD
    substeps: int | None = None
    window: int | str | None = None
    window_max: int = WINDOW_MAX

    def __post_init__(self) -> None:
        check_hold(self.hold)
        check_window("MapEstimator", self.window, self.window_max, self.system)
        if self.window is not None and self._by_times:
            raise OptionError("MapEstimator: window bounds the fits of the information "
                              "schedule; a schedule with times has its own blocks "
                              "(full_window): give one or the other.")

    @property
    def _by_times(self) -> bool:
        """A schedule with fit times in seconds was given (else: information schedule)."""
        return self.schedule is not None and self.schedule.times is not None

    def _schedule(self) -> FitSchedule:
        if self.schedule is not None:
            return replace(self.schedule, hold=self.hold).given_substeps(self.substeps)
        return FitSchedule(system=self.system, full_window=math.inf, noise_std=self.noise_std,
                           hold=self.hold, compiled=self.compiled).given_substeps(self.substeps)

    def _record_schedule(self, t: FloatArray, U: FloatArray, Y: FloatArray, st0: MapState
                         ) -> FitSchedule:
        """The schedule of one record, with its sub-steps chosen at the start values."""
        sched = self._schedule()
        if sched.substeps is not None:
            return sched
        if self.noise_std is None and t.shape[0] < MIN_SAMPLES:
            return replace(sched, substeps=1)
        sigma = resolve_noise_std(self.noise_std, Y)
        n = choose_substeps(model_kernel(self.system, compiled=self.compiled), t, U, Y,
                            st0.theta_hat0, st0.x_hat0, sigma, hold=self.hold,
                            h_rho=sched.h_rho)
        return replace(sched, substeps=n)

    def fit_samples(self, t: FloatArray) -> list[int]:
        """The sample counts k₁ at which :meth:`run` fits (window 0 … k₁ − 1) on record ``t``.

        Parameters
        ----------
        t : ndarray (N,)

        Returns
        -------
        list of int
            Increasing; the last is N (the whole record) whenever N admits a fit.
        """
        return self._schedule().fit_samples(t, growth=self.growth, least=self._min_samples())

    def _min_samples(self) -> int:
        """Samples a window needs before a fit (σ estimated from it unless given)."""
        return 3 if self.noise_std is not None else MIN_SAMPLES

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None
             ) -> MapState:
        """The state before the first sample: x̂(0), θ̂(0) (θ̂(0) in Θ, default the centre).

        Parameters
        ----------
        x_hat0 : array_like (n,), optional
            Default zeros.
        theta_hat0 : array_like (p,), optional
            Default the centre of Θ.

        Returns
        -------
        MapState

        Raises
        ------
        ParameterSetError
            θ̂(0) outside Θ.
        """
        x0, th0 = start_values(self.system, x_hat0, theta_hat0)
        return MapState(x_hat0=x0, theta_hat0=th0, x_hat=x0, theta_hat=th0,
                        theta_sd=theta_prior_sd(self.system))

    def _check_state(self, state: Any) -> MapState:
        """``state`` if it is a :class:`MapState` of this model (:func:`check_state`)."""
        n, r, p = self.system.n, self.system.r, self.system.p
        return check_state("MapEstimator", state, MapState,
                           {"x_hat0": (n,), "theta_hat0": (p,), "x_hat": (n,),
                            "theta_hat": (p,), "theta_sd": (p,), "P": (n + p, n + p),
                            "R": (r, r), "Q_x": (n, n)})

    def step(self, state: MapState, u: ArrayLike | None, y: ArrayLike, dt: float) -> MapState:
        """Append the samples of one instant and run the fits whose window ends here.

        The default schedule fits all the samples so far when their count reaches one of
        :func:`~.map_fit.information_schedule`'s (with a window W, past W: every W samples,
        the samples since the previous fit, and the log keeps only those); a given
        ``schedule`` fits at the last sample with elapsed time ≤ t_j (``dt`` says the next
        sample comes after t_j). These are the fits :meth:`run` makes, except its last:
        ``run`` also fits the whole record at its end, which a stream does not have. Between
        fits the estimates are the joint EKF's, started from the latest fit
        (:func:`fit_as_prior`). The fits run in the caller (a ``step``
        that fits takes as long as the fit).

        Parameters
        ----------
        state : MapState
            From :meth:`init` or the previous ``step``. States of one stream share its data
            log: step each state once, in order.
        u : array_like (m,)
            ``None`` when m = 0.
        y : array_like (r,)
            NaN: a missing sample (it does not enter the fits).
        dt : float
            Time to the next sample, > 0.

        Returns
        -------
        MapState
            The estimates at this sample: row k of :meth:`run` after k + 1 steps, for every
            row but the record's last (to the rounding of the accumulated sample times; see
            the protocol page).

        Raises
        ------
        StateError
            Not a :class:`MapState` of this model; a state of another estimator's stream; a
            state stepped already (not the latest of its stream).
        DimensionError
            Wrong shapes or dt ≤ 0.
        NonFiniteError
            NaN or inf in u, or inf in y; the EKF between fits diverged.
        InputLimitError
            u, y or dt of a magnitude float64 arithmetic cannot take (rescale the unit).
        """
        sys_ = self.system
        n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
        log = getattr(state, "log", None)
        if log is None or state is not log.last:    # (the state the stream returned: checked)
            state = self._check_state(state)
        u_, y_, h = stream_sample(sys_, u, y, dt)
        if state.log is None:
            log = _MapLog(m, r, self)
            log.sched, log.hold = self._schedule(), streamable(self.hold, "MapEstimator")
            log.prior0 = log.sched.initial_prior(state.x_hat0, state.theta_hat0)
        else:
            log = state.log
        if log.owner is not self:
            raise StateError("MapEstimator.step: this state's stream was started by another "
                             "MapEstimator (its log and fits are that estimator's); step it "
                             "with that one, or start a stream of this one from init().")
        if log.offset + log.size != state.k:
            raise StateError(f"MapEstimator.step: this state is not the latest of its stream "
                             f"(it has {state.k} samples, its stream {log.offset + log.size}: it was "
                             f"stepped already); step each state once, in order, from "
                             f"init().")
        elapsed = 0.0 if state.k == 0 else state.elapsed + state.dt_prev
        ut, u_hist = stage2_samples(u_[None], log.hold, state.u_history)
        u_ = ut[0]
        log.append(elapsed, u_, y_)
        sched, prior0 = log.sched, log.prior0
        k1 = state.k + 1
        j, fits, ends = state.j, list(state.fits), list(state.fit_samples)
        W = self._stream_window(state, sched, log, k1, prior0)
        due = False
        if sched.times is not None:             # times (s): due when the next sample is later
            while sched.times(j) + 1e-12 < elapsed + h:
                due, j = True, j + 1
        else:                                   # sample counts of the information schedule
            at = log.counts.get(W)
            if at is None:
                at = sched.sample_counts(self.growth)
                at = log.counts[W] = at if W is None else windowed_counts(at, W)
            while at(j) <= k1:
                due, j = due or at(j) == k1, j + 1
        x, th, sd = state.x_hat, state.theta_hat, state.theta_sd
        P, R, Q_x = state.P, state.R, state.Q_x
        nsub = state.substeps
        fitted = refused = False
        anchor, rejected = state.anchor, state.rejected
        if due and k1 >= self._min_samples():   # a fit: its estimates replace this sample's
            windowed_fit = W is not None and k1 > W and anchor is not None
            fit = self._stream_fit(sched, log, k1, fits, prior0,
                                   anchor if windowed_fit else None)
            why = why_not_applied(fit, fits[-1] if fits else None) if windowed_fit else None
            if why is None:
                fits.append(fit)
                ends.append(state.k)
                x, th, sd = fit.x_end, fit.theta, fit.theta_se
                _, P, R, Q_x = fit_as_prior(sys_, fit, sample_interval(log.T[:log.size]))
                nsub = fit.substeps
                fitted = True
                if W is not None:
                    anchor = (state.k, np.concatenate([fit.x_end, fit.theta]), fit.cov_end,
                              fit.noise_std)
            else:                               # the EKF steps this sample (below)
                if not rejected:                # once a stream: the first, as it happens
                    _warn_rejected("MapEstimator.step", [why], None)
                rejected, refused = rejected + (why,), True
            if W is not None and k1 >= W:       # the next window starts here
                log.trim(state.k)
        prop = Propagation(hold=self.hold, substeps=nsub, h_rho=sched.h_rho)
        if fitted:
            pass                                # the fit's estimates
        elif state.k > 0 and P is not None and Q_x is not None:    # the EKF from the latest fit
            s_ = np.concatenate([x, th])
            P = np.array(P, dtype=np.float64, order="C")
            ekf_sample(ekf_kernels(sys_, compiled=self.compiled), sys_, s_, P,
                       log.U[state.k - 1 - log.offset].copy(), u_, y_, state.dt_prev, prop,
                       Q_x, R,
                       state.k)
            x, th, sd = s_[:n], s_[n:], np.sqrt(np.maximum(np.diag(P)[n:], 0.0))
            if refused:                         # the next window's arrival cost
                anchor = (state.k, s_.copy(), P.copy(), fits[-1].noise_std)
        elif state.k > 0:                       # no fit yet: the model from θ̂(0)
            model = model_kernel(sys_, compiled=self.compiled)
            pc, WT = prop.arrays()
            U2 = np.ascontiguousarray(np.stack([log.U[state.k - 1 - log.offset], u_]),
                                      dtype=np.float64)
            x = np.asarray(model.propagate(np.array(x), np.array(th), U2, 0, state.dt_prev,
                                           pc, WT, n < 0, np.empty((n, n)),
                                           np.empty((n, p))))
        log.last = MapState(x_hat0=state.x_hat0, theta_hat0=state.theta_hat0,
                            x_hat=np.array(x), theta_hat=np.array(th), theta_sd=np.array(sd),
                            k=state.k + 1, elapsed=elapsed, j=j, fits=tuple(fits),
                            fit_samples=tuple(ends), dt_prev=h, log=log, u_history=u_hist,
                            P=P, R=R, Q_x=Q_x, substeps=nsub, window=W, anchor=anchor,
                            rejected=rejected)
        return log.last

    def _stream_window(self, state: MapState, sched: FitSchedule, log: _MapLog, k1: int,
                       prior0: tuple[FloatArray, FloatArray]) -> int | None:
        """The stream's window at sample count k1: as given, or ``"auto"`` decided on the
        samples so far at the counts of :func:`~.window.window_grid` (the rule of
        :func:`~.window.resolve_window`, so that the stream's W is the record's)."""
        if self.window is None or state.window is not None:
            return state.window
        if self.window != "auto":
            return int(self.window)
        return stream_window(sched, log.T, log.U, log.Y, k1, prior0, self.window_max,
                             window_grid(self.system, self.window_max))

    def _stream_fit(self, sched: FitSchedule, log: _MapLog, k1: int, fits: list[FitResult],
                    prior0: tuple[FloatArray, FloatArray],
                    anchor: tuple[int, FloatArray, FloatArray, FloatArray] | None
                    ) -> FitResult:
        """The fit due at sample count k1 of a stream: of all its data, or of its window (the
        log's samples since ``anchor``'s, with its (s, P, σ) as arrival cost)."""
        prev = fits[-1] if fits else None
        n = log.size
        if anchor is not None:
            k0 = anchor[0]
            fit = fit_window(sched, log.T[:n], log.U[:n], log.Y[:n], k0=k0 - log.offset,
                             k1=k1 - log.offset, s0=anchor[1], P0=anchor[2],
                             noise_std=anchor[3])
            return replace(fit, k0=k0, k1=k1)
        if self._by_times:
            return sched.fit(log.T[:k1], log.U[:k1], log.Y[:k1], k1, prev, prior0)
        return fit_record(sched, log.T[:k1], log.U[:k1], log.Y[:k1], k1, prev, prior0)

    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            state0: MapState | None = None, throw: bool = True,
            fit_progress: FitProgress | None = None) -> EstimateResult:
        """Fit on the schedule over a record; between fits, the EKF continued from the latest.

        Parameters
        ----------
        t : array_like (N,)
        u : array_like (N, m) or (N,)
        y : array_like (N, r) or (N,)
        state0 : MapState, optional
            From :meth:`init` (default ``init()``); a record starts a new experiment, so a
            state that has already been stepped is refused.
        throw : bool
            What a failure does (:mod:`~thetahat.estimation.status`): True (default) raises
            its error; False returns the result with ``status``
            :attr:`~thetahat.estimation.status.Status.DIVERGED` (the EKF between fits
            diverged, or a fit came back non-finite or raised one) or
            :attr:`~thetahat.estimation.status.Status.SINGULAR` (a fit's information could
            not be decomposed), its ``message`` and NaN rows from ``failed_at`` on (a failed
            fit: from the last sample of its window).
        fit_progress : callable, optional
            ``fit_progress(done, total)`` (:data:`thetahat.progress.FitProgress`), called in
            the caller's thread: ``(0, total)`` before the first fit, then ``(done, total)``
            after each. ``total`` is the number of scheduled fits (:meth:`fit_samples` on
            ``t``), known before the first; the last call is ``(total, total)``, also when a
            fit fails and ``throw`` is False (the run stops there). The fits are not equal
            work: by default each takes all the data so far, so the last ones are the
            longest. An exception it raises (a ``KeyboardInterrupt`` too) ends the run and
            propagates unchanged. It does not change the estimates.

        Returns
        -------
        EstimateResult
            Row k: at a fit's last sample the fit's estimates; after it, the joint EKF's
            started from the fit (:func:`fit_as_prior`: the fit is the arrival cost of the
            samples before); before the first fit θ̂(0) and the model's x̂. The last row is
            the MAP estimate of the whole record. ``diagnostics`` is a
            :class:`MapDiagnostics` (standard errors and the fits).

        Raises
        ------
        OptionError
            ``state0`` has been stepped (continue that stream with :meth:`step`).
        NonFiniteError
            ``throw=True`` and the run failed (see ``throw``).
        """
        sys_ = self.system
        t_, U_raw, Y = check_record(t, u, y, m=sys_.m, r=sys_.r)
        U = stage2_samples(U_raw, self.hold)[0]       # stage 2's samples (the stream's: step)
        st0 = self.init() if state0 is None else self._check_state(state0)
        if st0.k:
            raise OptionError("MapEstimator.run starts an experiment from init(); this state0 "
                              "has been stepped: continue its stream with step.")
        N, p = t_.shape[0], sys_.p
        sched = self._record_schedule(t_, U, Y, st0)
        # the fits' failure is raised (throw) only once the EKF between the fits before it
        # has run: the run stops at its first failure, whichever it is
        # the stream's rule: the sub-steps as given (1 by default), not the record's choice
        W = resolve_window(self.window, self.window_max, replace(sched, substeps=self.substeps),
                           t_, U, Y, sched.initial_prior(st0.x_hat0, st0.theta_hat0))
        fits, ends, stop, rejected = self._fits(sched, t_, U, Y, st0, False, fit_progress, W)
        TH = np.empty((N, p))
        SD = np.empty((N, p))
        TH[:] = st0.theta_hat0
        SD[:] = theta_prior_sd(sys_)
        X = self._first_predictions(sched, t_, U, Y, st0, ends[0] + 1 if ends
                                    else N if stop is None else max(stop.at, 1))
        stop = self._between_fits(sched, t_, U, Y, fits, ends, X, TH, SD, stop)
        if stop is not None:                    # the fits the run reached
            reached = bisect.bisect_left(ends, stop.at)
            fits, ends = fits[:reached], ends[:reached]
        diag = MapDiagnostics(theta_sd=SD, fits=tuple(fits),
                              fit_samples=np.array(ends, dtype=np.int64),
                              substeps=max([sched.substeps or 1]
                                           + [f.substeps for f in fits]),
                              rejected=tuple(rejected))
        if rejected:
            _warn_rejected("MapEstimator.run", rejected, len(rejected) + len(fits))
        res = stopped_result(t=t_, x_hat=X, theta_hat=TH,
                             phi_hat=model_phi_hat(sys_, U_raw, Y, X, TH, stop),
                             skipped=missing_samples(Y), diagnostics=diag, stop=stop,
                             blank=(SD,))
        return res.raise_for_status() if throw else res

    def _fits(self, sched: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
              st0: MapState, throw: bool, fit_progress: FitProgress | None = None,
              W: int | None = None
              ) -> tuple[list[FitResult], list[int], RunStop | None, list[str]]:
        """The scheduled fits of a record, in order, until one fails: (fits applied, their
        last samples, the failure or None, why the others were not applied). With ``throw`` a
        fit's error is raised at once. ``fit_progress(done, total)`` before the first fit and
        after each (see :meth:`run`). With a window W, the fits past W are of the samples
        since the previous fit, with its posterior as arrival cost; a window fit that
        :func:`~.map_fit.why_not_applied` refuses is not applied, and the next window's
        arrival cost is then the EKF's posterior at its end (the EKF carried on from the last
        fit applied, as the rows are)."""
        prior0 = sched.initial_prior(st0.x_hat0, st0.theta_hat0)
        fits: list[FitResult] = []
        ends: list[int] = []
        rejected: list[str] = []
        anchor: tuple[int, FloatArray, FloatArray, FloatArray] | None = None
        carry: _Carry | None = None
        ks = windowed(self.fit_samples(t), W)
        if fit_progress is not None:
            fit_progress(0, len(ks))
        for i, k1 in enumerate(ks):
            prev = fits[-1] if fits else None
            last = i == len(ks) - 1
            if not self._by_times and last and prev is not None:
                # the record's own fit: iterate to convergence, not to the warm-start budget
                sched = replace(sched, max_iter=sched.first_max_iter)
            windowed_fit = W is not None and k1 > W and anchor is not None
            try:
                if windowed_fit and anchor is not None:
                    fit = fit_window(sched, t, U, Y, k0=anchor[0], k1=k1, s0=anchor[1],
                                     P0=anchor[2], noise_std=anchor[3], final=last)
                elif self._by_times:
                    fit = sched.fit(t, U, Y, k1, prev, prior0)
                else:
                    fit = fit_record(sched, t, U, Y, k1, prev, prior0, final=last)
                stop = fit_stop(fit)
            except NonFiniteError as exc:
                if throw:
                    raise
                stop = RunStop(Status.DIVERGED, str(exc), k1 - 1)
            except np.linalg.LinAlgError as exc:
                stop = RunStop(Status.SINGULAR, f"the MAP fit of samples 0…{k1 - 1} failed: "
                               f"its information matrix could not be decomposed ({exc}); the "
                               "model's trajectory is not finite from these start values, or "
                               "the record does not determine (x(0), θ): check the model, "
                               "theta_hat0 and noise_std.", k1 - 1)
            why = why_not_applied(fit, prev) if stop is None and windowed_fit else None
            if why is not None and prev is not None:
                # not applied: the next window starts here from the EKF's posterior
                carry, stop = self._carry(sched, t, U, Y, prev, ends[-1], carry, k1)
                if stop is None:
                    rejected.append(why)
                    anchor = (k1 - 1, carry.s.copy(), carry.P.copy(), prev.noise_std)
            if stop is not None:
                if throw:
                    raise stop.error()
                if fit_progress is not None:    # the run stops here: no fit is left
                    fit_progress(len(ks), len(ks))
                return fits, ends, stop, rejected
            if why is None:
                fits.append(fit)
                ends.append(k1 - 1)
                carry = None
                if W is not None:
                    anchor = (k1 - 1, np.concatenate([fit.x_end, fit.theta]), fit.cov_end,
                              fit.noise_std)
            if fit_progress is not None:
                fit_progress(i + 1, len(ks))
        return fits, ends, None, rejected

    def _carry(self, sched: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
               fit: FitResult, e: int, carry: _Carry | None, k1: int
               ) -> tuple[_Carry, RunStop | None]:
        """The EKF from ``fit`` (applied at sample e), or on from ``carry``, through sample
        k1 − 1: the rows :meth:`_between_fits` computes there (:meth:`_ekf_span`), kept for
        the arrival cost of the window that starts at k1 − 1."""
        if carry is None:
            s, P, R, Q_x = self._ekf_start(t, fit, e)
            carry = _Carry(k=e + 1, s=s, P=np.array(P, dtype=np.float64, order="C"), R=R,
                           Q_x=Q_x)
        if carry.k >= k1:
            return carry, None
        N, n, p = t.shape[0], self.system.n, self.system.p
        stop = self._ekf_span(sched, t, U, Y, fit, (carry.s, carry.P, carry.R, carry.Q_x),
                              carry.k, k1, (np.empty((N, n)), np.empty((N, p)),
                                            np.empty((N, p)), np.full(N, np.nan)))
        return replace(carry, k=k1), stop

    def _ekf_start(self, t: FloatArray, fit: FitResult, e: int
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(s, P, R, Q_x): the EKF started from ``fit``, applied at sample e
        (:func:`fit_as_prior`)."""
        return fit_as_prior(self.system, fit, sample_interval(t[fit.k0:e + 1]))

    def _ekf_span(self, sched: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
                  fit: FitResult, state: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
                  k0: int, k1: int,
                  rows: tuple[FloatArray, FloatArray, FloatArray, FloatArray]
                  ) -> RunStop | None:
        """The EKF over samples k0 … k1 − 1 from ``state`` = (s, P, R, Q_x) at k0 − 1 (s and P
        advanced in place), with ``fit``'s sub-steps, into ``rows`` = (X, TH, SD, NIS); the
        run's stop where it diverges, else None."""
        sys_ = self.system
        kern = ekf_kernels(sys_, compiled=self.compiled)
        ts = stage2_set(sys_.require_parameter_set("the MAP estimator"))
        pc, WT = Propagation(hold=sched.hold, substeps=fit.substeps, h_rho=sched.h_rho).arrays()
        s, P, R, Q_x = state
        X, TH, SD, nis = rows
        bad = kern.loop(s, P, U, Y, t, k0, k1, R, ts.lo, ts.hi, ts.ell, pc, WT, Q_x, X, TH, SD,
                        nis)
        if bad >= 0:
            return RunStop(Status.DIVERGED, divergence_message(t, bad, nis, sys_.r), bad)
        return None

    def _first_predictions(self, sched: FitSchedule, t: FloatArray, U: FloatArray,
                           Y: FloatArray, st0: MapState, k1: int) -> FloatArray:
        """x̂ before the first fit (rows 0 … k1 − 1): the model run from x̂(0) with θ̂(0)."""
        sys_ = self.system
        n, p, N = sys_.n, sys_.p, t.shape[0]
        sweep = sweep_kernel(model_kernel(sys_, compiled=self.compiled))
        X = np.empty((N, n))
        A, b, T = np.empty((n + p, n + p)), np.empty(n + p), np.empty((n, n + p))
        seg = np.empty((k1, n))
        pc, WT = Propagation(hold=sched.hold, substeps=sched.substeps or 1,
                             h_rho=sched.h_rho).arrays()
        sweep(np.array(st0.x_hat0, dtype=np.float64), np.array(st0.theta_hat0, dtype=np.float64),
              U, Y, t, 0, k1, False, np.ones(sys_.r), pc, WT, False, A, b, T, seg)
        X[:k1] = seg
        return X

    def _between_fits(self, sched: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
                      fits: list[FitResult], ends: list[int], X: FloatArray, TH: FloatArray,
                      SD: FloatArray, stop: RunStop | None) -> RunStop | None:
        """Rows from each fit's last sample to the next fit's: the fit, then the EKF from it
        (up to ``stop``, where a fit failed). Returns the run's first failure, or None."""
        last = t.shape[0] if stop is None else stop.at
        nis = np.full(t.shape[0], np.nan)
        for i, (fit, e) in enumerate(zip(fits, ends)):
            end = ends[i + 1] if i + 1 < len(ends) else last
            X[e], TH[e], SD[e] = fit.x_end, fit.theta, fit.theta_se
            if e + 1 >= end:
                continue
            failed = self._ekf_span(sched, t, U, Y, fit, self._ekf_start(t, fit, e), e + 1, end,
                                    (X, TH, SD, nis))
            if failed is not None:
                return failed
        return stop



def fit_stop(fit: FitResult) -> RunStop | None:
    """None when a fit may be used (its θ and x at its window's end are finite), else why not.

    Parameters
    ----------
    fit : FitResult

    Returns
    -------
    RunStop or None
        :attr:`~thetahat.estimation.status.Status.DIVERGED` at the window's last sample.
    """
    if np.all(np.isfinite(fit.theta)) and np.all(np.isfinite(fit.x_end)):
        return None
    return RunStop(Status.DIVERGED, f"the MAP fit of samples {fit.k0}…{fit.k1 - 1} came back "
                   "non-finite (θ or x at its window's end): the model's trajectory is not "
                   "finite there; check the model, theta_hat0 and noise_std.", fit.k1 - 1)
