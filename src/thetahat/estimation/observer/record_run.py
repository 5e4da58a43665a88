"""The observer's run over a record, shared by every back end: its loop, its status, its result.

What lives here:

* :data:`HOLDS` (the sample holds of ``run``) and :data:`PROGRESS_EVERY` (how often ``run``
  calls its progress callback);
* :func:`integrate_record` and :func:`integrate_records`, the NumPy loops of
  :func:`~thetahat.estimation.observer.step.advance` over one record and over B records that
  share a time grid (:meth:`ModifiedHighGainObserver.run
  <thetahat.estimation.observer.observer.ModifiedHighGainObserver.run>`,
  :func:`~thetahat.estimation.observer.batch_run.run_batch`); a failed step stops its row and
  comes back as a :class:`Failure`, not as an exception;
* :class:`Failure` and :func:`failure`: the one description of a failed step in every back end
  (NumPy, numba's kernel, the generated C): its :class:`~thetahat.estimation.status.Status`,
  the step, and the sentence that names the sample and the fix;
* :class:`RecordRows`, the outputs of a run filled a block of state rows at a time (a compiled
  run writes :data:`ROW_BLOCK` rows into scratch and copies their columns out, so a record is
  never held as state rows and as outputs at once);
* :func:`states_result` and :func:`observer_result`, the
  :class:`~thetahat.estimation.protocol.EstimateResult` of a run from its state rows — OK, or
  stopped at ``failed_at`` with the rows from there NaN (``throw=False``); with ``throw=True``
  a run raises :meth:`Failure.error` instead, the
  :func:`~thetahat.estimation.status.status_error` of its status and message.

**The hold.** Samples are held constant over a sampling interval (``"zoh"``: causal, what
``step`` does, identical to a loop of ``step``) or interpolated linearly to the next sample
(``"foh"``: ``run`` only, one more evaluation of g per step). A ZOH delays smooth signals by
half a sample, which dominates the error: on the DC motor of Sec. VIII (θ known, ε = 1,
noise-free; ω up to 3.8 rad/s, φ up to 3.8 N m) the largest errors after convergence were

========  ======  ================  ================
rate      hold    |ω − ω̂| (rad/s)   |φ − φ̂| (N m)
========  ======  ================  ================
1 kHz     zoh     1.1e-2            1.3e-3
1 kHz     foh     6.4e-4            9.6e-5
10 kHz    zoh     9.7e-4            1.1e-4
10 kHz    foh     9.4e-6            9.7e-7
========  ======  ================  ================

**Rows and the failed step.** Row k of a run holds the state at ``t[k]``, before sample k is
processed. When the step from ``t[i]`` fails (its new state would be NaN, inf or above
:data:`~thetahat.estimation.observer.formulas.DIVERGENCE_BOUND`, its implicit matrix is
singular, or θ* is invalid under ``on_invalid='raise'``), rows 0 … i are as computed and the
result's ``failed_at`` is i + 1: the first row the run could not compute; the message names
the step ("in the step from t[i] = …").

What it may import: the step and the plan of this room (:mod:`.step`, :mod:`.plan`,
:mod:`.formulas`), the laws' error of an invalid θ*, and the bottom of
:mod:`thetahat.estimation` (protocol, status). Never the observer class, which imports it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import OptionError, ThetahatError, UpdateLawError
from ...model.perturbation import Perturbation
from ..hold import check_hold as any_hold
from ..protocol import EstimateResult, ObserverDiagnostics
from ..status import Status, status_error
from .formulas import DIVERGENCE_BOUND
from .laws import UpdateLaw
from .laws.inversion import invalid_theta_star_error
from .plan import StateLayout, StepPlan
from .step import advance, diverged, readout

__all__ = ["COMPILED", "Failure", "HOLDS", "PROGRESS_EVERY", "ROW_BLOCK", "RecordRows",
           "check_compiled", "check_hold", "failure", "failure_message", "integrate_record",
           "integrate_records", "observer_result", "row_blocks", "states_result", "step_error"]

FloatArray = NDArray[np.float64]
Progress = Callable[[int, int], None]

#: The sample holds of ``run``: ``"zoh"`` holds the samples over a step (causal, what ``step``
#: does), ``"foh"`` interpolates them linearly to the next sample.
HOLDS = ("zoh", "foh")
#: Samples between two calls of ``run``'s progress callback.
PROGRESS_EVERY = 1_000
#: State rows a compiled run writes into scratch before their columns are copied to the
#: outputs (:class:`RecordRows`): 2¹⁶ rows of LuGre's 6-entry state are 3 MB, against 48 MB for
#: 10⁶ samples held whole; a kernel call on that many rows costs its arithmetic, not its call.
ROW_BLOCK = 1 << 16
#: Where ``run`` runs (the observer's ``compiled``): False, the NumPy step; None, the fastest
#: back end where it pays; True, the fastest back end that takes the observer.
COMPILED = (False, None, True)


def check_hold(hold: object) -> str:
    """``hold`` if the observer's ``run`` takes it (:data:`HOLDS`): a hold of
    :func:`thetahat.estimation.hold.check_hold` its exponential integrator can follow.

    Parameters
    ----------
    hold : str

    Returns
    -------
    str

    Raises
    ------
    OptionError
        Not a hold at all, or ``"bandlimited"`` (the statistical methods take it).

    Examples
    --------
    >>> check_hold("foh")
    'foh'
    """
    if any_hold(hold) not in HOLDS:
        raise OptionError(f"hold {hold!r} reaches the statistical methods (guarded's stage 2, "
                          f"mle, ekf); the paper's observer takes {' or '.join(HOLDS)}: choose "
                          "one of those or another method.")
    return str(hold)


def check_compiled(compiled: object) -> bool | None:
    """``compiled`` if it is one of :data:`COMPILED` (False, None or True, not 0 or 1).

    Parameters
    ----------
    compiled : object

    Returns
    -------
    bool or None

    Raises
    ------
    OptionError
        Another value.

    Examples
    --------
    >>> check_compiled(None) is None
    True
    """
    if compiled is None or isinstance(compiled, bool):
        return compiled
    raise OptionError(f"compiled must be one of {COMPILED}; got {compiled!r}.")


@dataclass(frozen=True, slots=True)
class Failure:
    """A step that failed: why, where, and the sentence of its error.

    Attributes
    ----------
    status : Status
        Not ``OK``.
    step : int
        The step from ``t[step]`` failed (rows 0 … step are as computed).
    message : str
        Where, what and the fix (:func:`failure_message`).
    """

    status: Status
    step: int
    message: str

    @property
    def failed_at(self) -> int:
        """The first row the run could not compute: ``step + 1``."""
        return self.step + 1

    def error(self) -> ThetahatError:
        """The exception of ``throw=True``: :func:`~thetahat.estimation.status.status_error`."""
        return status_error(self.status, self.message)


def failure_message(status: Status, where: str, law: str) -> str:
    """The sentence of a failed step, the same in every back end.

    Parameters
    ----------
    status : Status
        ``DIVERGED``, ``SINGULAR`` or ``THETA_STAR`` (any other code reads as a divergence
        with its :data:`~thetahat.estimation.status.MESSAGES` text added).
    where : str
        The step, e.g. ``"in the step from t[12] = 0.012"``.
    law : str
        The update law's name (the θ* message names it).

    Returns
    -------
    str

    Examples
    --------
    >>> text = failure_message(Status.SINGULAR, "in the step from t[3] = 0.003", "GradientInversion")
    >>> "t[3]" in text and "decrease dt or increase ε" in text
    True
    """
    if status == Status.THETA_STAR:
        text = str(invalid_theta_star_error(law, 1))
        return f"{text[:-1] if text.endswith('.') else text} ({where})."
    return (f"the observer state diverged (NaN, inf, a norm above {DIVERGENCE_BOUND:g}, or a "
            f"singular implicit step) {where}: the gains are too high for this dt (decrease dt "
            "or increase ε), or the update law / data scaling is off.")


def failure(status: int, step: int, t: FloatArray, law: str, run: int | None = None
            ) -> Failure:
    """The :class:`Failure` of the step from ``t[step]`` that ended with ``status``.

    Parameters
    ----------
    status : int
        A nonzero :class:`~thetahat.estimation.status.Status` code (of any back end).
    step : int
    t : ndarray, shape (N,)
        The record's instants.
    law : str
        The update law's name.
    run : int, optional
        The row of a batch (named in the message).

    Returns
    -------
    Failure

    Examples
    --------
    >>> import numpy as np
    >>> f = failure(4, 2, np.array([0.0, 0.5, 1.0, 1.5]), "ConstantLaw")
    >>> f.status.name, f.failed_at, "t[2] = 1.0" in f.message
    ('DIVERGED', 3, True)
    """
    code = Status(status)
    where = ("" if run is None else f"of run {run} ") + \
        f"in the step from t[{step}] = {float(t[step])!r}"
    return Failure(status=code, step=int(step), message=failure_message(code, where, law))


def step_error(status: int, law: str) -> ThetahatError:
    """The error of one failed ``step`` (streaming), the same in every back end.

    Parameters
    ----------
    status : int
        A nonzero :class:`~thetahat.estimation.status.Status` code.
    law : str
        The update law's name.

    Returns
    -------
    ThetahatError
        :func:`~thetahat.estimation.status.status_error` of the status, its message saying
        "in this step".

    Examples
    --------
    >>> type(step_error(4, "ConstantLaw")).__name__
    'NonFiniteError'
    """
    code = Status(status)
    return status_error(code, failure_message(code, "in this step", law))


def _theta_star_failed(exc: UpdateLawError) -> bool:
    """Whether an update law's error is the invalid θ* of ``on_invalid='raise'``
    (:attr:`Status.THETA_STAR`), not another misuse of the law."""
    return "theta_star is NaN or inf" in str(exc)


def integrate_record(plan_for: Callable[[float], StepPlan], pert: Perturbation,
                     law: UpdateLaw, S: FloatArray, t: FloatArray, dts: FloatArray,
                     U: FloatArray, Y: FloatArray, ok: NDArray[np.bool_], foh: bool,
                     progress: Progress | None = None) -> Failure | None:
    """The states of one record into ``S`` (N, size), whose row 0 holds the initial state.

    Parameters
    ----------
    plan_for : callable
        ``plan_for(dt)`` → the observer's :class:`~thetahat.estimation.observer.plan.StepPlan`.
    pert, law
        As for :func:`~thetahat.estimation.observer.step.advance`.
    S : ndarray, shape (N, size)
        Filled row by row; rows after a failed step are left as they were.
    t, dts : ndarray, shapes (N,), (N - 1,)
    U, Y : ndarray, shapes (N, m), (N, r)
    ok : ndarray of bool, shape (N,)
        Samples whose y is present.
    foh : bool
        First-order hold.
    progress : callable, optional
        ``progress(done, total)`` every :data:`PROGRESS_EVERY` samples and at the end.

    Returns
    -------
    Failure or None
        The failed step, or None when every step succeeded.

    Raises
    ------
    UpdateLawError
        A misuse of the law other than an invalid θ* (e.g. a weight l outside [0, 1]).
    """
    s = S[0]
    N = S.shape[0]
    name = type(law).__name__
    plans: dict[float, StepPlan] = {}
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for i in range(N - 1):
            if progress is not None and i % PROGRESS_EVERY == 0:
                progress(i, N - 1)
            dt = float(dts[i])
            plan = plans.get(dt)
            if plan is None:
                plan = plans[dt] = plan_for(dt)
            try:
                if foh:
                    s = advance(plan, pert, law, s, U[i], Y[i], dt, bool(ok[i]), U[i + 1],
                                Y[i + 1] if ok[i + 1] else Y[i])
                else:
                    s = advance(plan, pert, law, s, U[i], Y[i], dt, bool(ok[i]))
            except UpdateLawError as exc:
                if not _theta_star_failed(exc):
                    raise
                return failure(Status.THETA_STAR, i, t, name)
            if diverged(s):
                return failure(Status.DIVERGED, i, t, name)
            S[i + 1] = s
    if progress is not None:
        progress(N - 1, N - 1)
    return None


def _advance_rows(plan: StepPlan, pert: Perturbation, law: UpdateLaw, s: FloatArray,
                  u0: FloatArray, y0: FloatArray, dt: float, correct: bool,
                  u1: FloatArray | None, y1: FloatArray | None
                  ) -> tuple[FloatArray, NDArray[np.int64]]:
    """One step of B rows: the new states and each row's status (an invalid θ* is found row by
    row, since the law reports it for the batch)."""
    try:
        nxt = advance(plan, pert, law, s, u0, y0, dt, correct, u1, y1)
    except UpdateLawError as exc:
        if not _theta_star_failed(exc):
            raise
        if s.shape[0] == 1:
            return np.full_like(s, np.nan), np.array([Status.THETA_STAR], dtype=np.int64)
        parts = [_advance_rows(plan.rows(np.array([b])), pert, law, s[b:b + 1], u0[b:b + 1],
                               y0[b:b + 1], dt, correct,
                               None if u1 is None else u1[b:b + 1],
                               None if y1 is None else y1[b:b + 1])
                 for b in range(s.shape[0])]
        return (np.concatenate([p[0] for p in parts]),
                np.concatenate([p[1] for p in parts]))
    codes = np.where(diverged(nxt), int(Status.DIVERGED), int(Status.OK)).astype(np.int64)
    return nxt, codes


def integrate_records(plan_for: Callable[[float], StepPlan], pert: Perturbation,
                      law: UpdateLaw, s0: FloatArray, t: FloatArray, dts: FloatArray,
                      U: FloatArray, Y: FloatArray, ok: NDArray[np.bool_], foh: bool, *,
                      throw: bool = True) -> tuple[FloatArray, list[Failure | None]]:
    """The states of B rows over a shared time grid; a row that fails stops, the others go on.

    Parameters
    ----------
    plan_for : callable
        ``plan_for(dt)`` → the plan of the B rows for that step length.
    pert, law
        As for :func:`~thetahat.estimation.observer.step.advance`.
    s0 : ndarray, shape (B, size)
    t, dts : ndarray, shapes (N,), (N - 1,)
    U, Y : ndarray, shapes (B, N, m), (B, N, r)
    ok : ndarray of bool, shape (B, N)
    foh : bool
    throw : bool
        Raise the first failure's error at once (the lowest row of the earliest failed step).

    Returns
    -------
    S : ndarray, shape (B, N, size)
        The rows of a failed run from its ``failed_at`` on are NaN.
    failures : list of (Failure or None), length B

    Raises
    ------
    NonFiniteError, UpdateLawError
        ``throw`` and a row failed (:meth:`Failure.error`).
    """
    B, N = U.shape[:2]
    S = np.full((B, N, s0.shape[1]), np.nan)
    S[:, 0] = s0
    out: list[Failure | None] = [None] * B
    alive = np.arange(B)
    s = s0
    name = type(law).__name__
    plans: dict[tuple[float, int], StepPlan] = {}
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for i in range(N - 1):
            dt = float(dts[i])
            plan = plans.get((dt, alive.size))
            if plan is None:
                full = plan_for(dt)
                plan = plans[(dt, alive.size)] = (full if alive.size == B
                                                  else full.rows(alive))
            u1 = U[alive, i + 1] if foh else None
            y1 = (np.where(ok[alive, i + 1, None], Y[alive, i + 1], Y[alive, i])
                  if foh else None)
            present = ok[alive, i]
            nxt = np.empty_like(s)
            codes = np.zeros(alive.size, dtype=np.int64)
            for flag in (True, False):
                rows = np.flatnonzero(present == flag)
                if rows.size == 0:
                    continue
                part = plan if rows.size == alive.size else plan.rows(rows)
                nxt[rows], codes[rows] = _advance_rows(
                    part, pert, law, s[rows], U[alive[rows], i], Y[alive[rows], i], dt, flag,
                    None if u1 is None else u1[rows], None if y1 is None else y1[rows])
            bad = np.flatnonzero(codes)
            for j in bad:
                out[int(alive[j])] = failure(int(codes[j]), i, t, name,
                                             None if B == 1 else int(alive[j]))
                if throw:
                    raise out[int(alive[j])].error()  # type: ignore[union-attr]
            if bad.size:
                keep = np.flatnonzero(codes == 0)
                alive, nxt = alive[keep], nxt[keep]
                plans.clear()
                if alive.size == 0:
                    break
            S[alive, i + 1] = nxt
            s = nxt
    return S, out


def states_result(lay: StateLayout, t: FloatArray, S: FloatArray, PHI: FloatArray,
                  present: NDArray[np.bool_], fail: Failure | None = None) -> EstimateResult:
    """The record's EstimateResult from its state rows (read-only copies).

    Parameters
    ----------
    lay : StateLayout
    t : ndarray, shape (N,)
    S : ndarray, shape (N, state_size)
        The state at each sample (rows from ``fail.failed_at`` on are not read).
    PHI : ndarray, shape (N, k)
        φ̂ at each sample.
    present : ndarray of bool, shape (N,)
        Whether each output sample was present (False: skipped).
    fail : Failure, optional
        The step that stopped the run: the result carries its status, message and
        ``failed_at``, and its rows from ``failed_at`` on are NaN.

    Returns
    -------
    EstimateResult

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> lay = lugre.observer().layout
    >>> res = states_result(lay, np.arange(3.0), np.zeros((3, lay.size)), np.zeros((3, lay.k)),
    ...                     np.array([True, False, True]))
    >>> res.theta_hat.shape, res.skipped.tolist(), res.theta_hat.flags.writeable, res.ok
    ((3, 1), [False, True, False], False, True)
    """
    rows = RecordRows(lay, S.shape[0])
    rows.put(0, S, PHI)
    return rows.result(t, present, fail)


def row_blocks(N: int, every: int) -> list[tuple[int, int]]:
    """The blocks ``(a, b)`` of a run over N samples, ``every`` steps each: rows a … b.

    Consecutive blocks share a row (b of one is a of the next): a block starts from the state
    its predecessor ended with.

    Parameters
    ----------
    N : int
        Samples (≥ 1).
    every : int
        Steps a block (≥ 1).

    Returns
    -------
    list of (int, int)

    Examples
    --------
    >>> row_blocks(6, 2)
    [(0, 2), (2, 4), (4, 5)]
    >>> row_blocks(1, 4)
    [(0, 0)]
    """
    return [(a, min(a + every, N - 1)) for a in range(0, max(N - 1, 1), every)] if N > 1 \
        else [(0, 0)]


class RecordRows:
    """The outputs of a run over N samples (x̂, θ̂, x̂₂ and φ̂), filled from state rows.

    A compiled run writes a block of full state rows (:data:`ROW_BLOCK` at most) into scratch
    and :meth:`put` copies the layout's columns out: the record is never held twice, as state
    rows and as outputs. :meth:`result` hands the arrays themselves to the result, read-only.

    Parameters
    ----------
    lay : StateLayout
    N : int

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> lay = lugre.observer().layout
    >>> rows = RecordRows(lay, 3)
    >>> S = np.arange(3.0 * lay.size).reshape(3, lay.size)
    >>> rows.put(0, S[:2], np.zeros((2, lay.k))); rows.put(2, S[2:], np.ones((1, lay.k)))
    >>> res = rows.result(np.arange(3.0), np.ones(3, dtype=bool))
    >>> bool((res.theta_hat == S[:, lay.theta]).all()), res.phi_hat[:, 0].tolist()
    (True, [0.0, 0.0, 1.0])
    """

    def __init__(self, lay: StateLayout, N: int) -> None:
        self.layout = lay
        self.x_hat = np.empty((N, lay.n))
        self.theta_hat = np.empty((N, lay.p))
        self.x_hat_refined = np.empty((N, lay.n)) if lay.second else None
        self.phi_hat = np.empty((N, lay.k))

    def put(self, a: int, S: FloatArray, PHI: FloatArray) -> None:
        """Copy state rows ``S`` and φ̂ rows ``PHI`` to rows a, a + 1, … of the outputs."""
        lay, b = self.layout, a + S.shape[0]
        self.x_hat[a:b] = S[:, lay.x]
        self.theta_hat[a:b] = S[:, lay.theta]
        if self.x_hat_refined is not None:
            self.x_hat_refined[a:b] = S[:, lay.x2]
        self.phi_hat[a:b] = PHI

    def result(self, t: FloatArray, present: NDArray[np.bool_],
               fail: Failure | None = None) -> EstimateResult:
        """The run's EstimateResult: the outputs, read-only, NaN from ``fail.failed_at`` on.

        Parameters
        ----------
        t : ndarray, shape (N,)
            Copied.
        present : ndarray of bool, shape (N,)
            Whether each output sample was present (False: skipped).
        fail : Failure, optional
            The step that stopped the run (rows from its ``failed_at`` on are not read).

        Returns
        -------
        EstimateResult
        """
        outs = [a for a in (self.x_hat, self.theta_hat, self.x_hat_refined, self.phi_hat)
                if a is not None]
        for a in outs:
            if fail is not None:
                a[fail.failed_at:] = np.nan
            a.setflags(write=False)

        def frozen(a: NDArray[Any]) -> NDArray[Any]:
            out = np.array(a, copy=True)
            out.setflags(write=False)
            return out

        return EstimateResult(
            t=frozen(t), x_hat=self.x_hat, phi_hat=self.phi_hat, theta_hat=self.theta_hat,
            skipped=frozen(~present),
            diagnostics=ObserverDiagnostics(x_hat_refined=self.x_hat_refined),
            status=Status.OK if fail is None else fail.status,
            message="" if fail is None else fail.message,
            failed_at=None if fail is None else fail.failed_at)


def observer_result(pert: Perturbation, C: FloatArray, lay: StateLayout, t: FloatArray,
                    S: FloatArray, U: FloatArray, Y: FloatArray, ok: NDArray[np.bool_],
                    fail: Failure | None = None) -> EstimateResult:
    """:func:`states_result` with φ̂ = g(v, x̂, θ̂) + z (3c) read out of the computed rows.

    Parameters
    ----------
    pert : Perturbation
    C : ndarray, shape (r, n)
    lay : StateLayout
    t : ndarray, shape (N,)
    S : ndarray, shape (N, state_size)
    U, Y : ndarray, shapes (N, m), (N, r)
    ok : ndarray of bool, shape (N,)
    fail : Failure, optional

    Returns
    -------
    EstimateResult
    """
    rows = S.shape[0] if fail is None else fail.failed_at
    PHI = np.full((S.shape[0], lay.k), np.nan)
    PHI[:rows] = readout(pert, C, S[:rows], U[:rows], Y[:rows], ok[:rows], lay)[1]
    return states_result(lay, t, S, PHI, ok, fail)

