"""The one status of every estimator and back end: how a step or a run ended, and its error.

:class:`Status` is what the step's formulas return (:func:`~thetahat.estimation.observer.formulas.
advance`, the update laws of :mod:`~thetahat.estimation.observer.laws.formulas`, the ``solve``
primitive), bound to NumPy, compiled by numba and printed as C; the generated C header's
``<NAME>_OK`` / ``<NAME>_ERR_…`` codes and their messages are derived from it
(:data:`thetahat.codegen.c_api.STATUS`), never copied by hand. The formulas read the codes as
the constants ``ST_<NAME>`` (:func:`status_constants`), which every binding provides.

One failure behaviour at the API boundary, for the observer, its compiled and C forms, the
joint EKF, the MAP fits and the guarded estimator alike: a step that ends with a status other
than :attr:`Status.OK` leaves the state unchanged and the run stops there. With ``throw=True``
(the default of every ``run`` and of the command line) it raises the
:class:`~thetahat.errors.ThetahatError` of :func:`status_error` — a
:class:`~thetahat.errors.NonFiniteError` for :attr:`Status.DIVERGED` and
:attr:`Status.SINGULAR`, an :class:`~thetahat.errors.UpdateLawError` for
:attr:`Status.THETA_STAR` — whose message names the sample and the fix; with ``throw=False`` it
returns an :class:`~thetahat.estimation.protocol.EstimateResult` whose ``status`` is that
status, whose ``message`` is that sentence and whose rows from ``failed_at`` on are NaN. A
singular implicit step is never an exception of NumPy's, nor ±inf that travels on. (A missing
sample, NaN in y, is not a failure: ``nan_policy`` decides, see
:mod:`~thetahat.estimation.records`.)
"""

from __future__ import annotations

from enum import IntEnum

from ..errors import NonFiniteError, ParameterSetError, ThetahatError, UpdateLawError

__all__ = ["Status", "MESSAGES", "status_constants", "status_error"]


class Status(IntEnum):
    """Status codes of the step in every back end (Python, numba, C).

    ``Status(code)`` gives the member of an int code (``Status(6)`` is ``Status.SINGULAR``).

    Examples
    --------
    >>> from thetahat.estimation.status import Status
    >>> int(Status.SINGULAR), Status(4).name
    (6, 'DIVERGED')
    """

    #: The step succeeded.
    OK = 0
    #: u holds NaN or inf, or y holds inf (checked by the C interface before the step).
    INPUT = 1
    #: y holds NaN and nan_policy='raise' (checked before the step).
    MISSING = 2
    #: θ* is NaN or inf where the excitation weight is positive (on_invalid='raise').
    THETA_STAR = 3
    #: φ̂ or the new state is NaN, inf or above the divergence bound.
    DIVERGED = 4
    #: θ̂₀ outside Θ, or a non-finite θ̂₀ / x̂₀ (the C interface's init).
    INIT = 5
    #: The implicit step's matrix I − γΦ₁N is singular (a zero pivot): no finite step exists.
    SINGULAR = 6


#: What each status means and what to do, in the words of the error messages and the C
#: interface's ``<name>_error_message``.
MESSAGES: dict[Status, str] = {
    Status.OK: "ok",
    Status.INPUT: "u holds NaN or inf, or y holds inf (only NaN marks a missing y)",
    Status.MISSING: ("y holds NaN and nan_policy='raise'; build the observer with "
                     "nan_policy='skip' to predict over missing samples, or clean the data"),
    Status.THETA_STAR: ("theta* is NaN or inf where the excitation weight is positive and "
                        "on_invalid='raise'; make l vanish there or use on_invalid='freeze'"),
    Status.DIVERGED: ("the observer state would diverge (norm above the bound, NaN or inf): "
                      "the gains are too high for this dt (decrease dt or increase eps), or "
                      "the data scaling is off; the state is unchanged"),
    Status.INIT: "theta_hat0 lies outside Theta, or theta_hat0 / x_hat0 is not finite",
    Status.SINGULAR: ("the implicit step is singular (I - gamma Phi1 N has a zero pivot): the "
                      "gains are too high for this dt (decrease dt or increase eps), or the "
                      "Jacobian of g is degenerate here; the state is unchanged"),
}


def status_constants() -> dict[str, int]:
    """The codes as the formulas read them: ``{"ST_OK": 0, …, "ST_SINGULAR": 6}``.

    Returns
    -------
    dict of str to int

    Examples
    --------
    >>> status_constants()["ST_THETA_STAR"]
    3
    """
    return {f"ST_{s.name}": int(s) for s in Status}


def status_error(status: Status, message: str | None = None) -> ThetahatError:
    """The exception a failed step or run raises (``throw=True``): one type per status.

    Parameters
    ----------
    status : Status
        Not :attr:`Status.OK`.
    message : str, optional
        The full sentence: where, what, and what to do (default :data:`MESSAGES`' text).

    Returns
    -------
    ThetahatError
        :class:`~thetahat.errors.UpdateLawError` for :attr:`Status.THETA_STAR`,
        :class:`~thetahat.errors.ParameterSetError` for :attr:`Status.INIT`,
        :class:`~thetahat.errors.NonFiniteError` otherwise.

    Examples
    --------
    >>> err = status_error(Status.SINGULAR)
    >>> type(err).__name__, "decrease dt" in str(err)
    ('NonFiniteError', True)
    """
    text = message or MESSAGES[Status(status)]
    if status == Status.THETA_STAR:
        return UpdateLawError(text)
    if status == Status.INIT:
        return ParameterSetError(text)
    return NonFiniteError(text)
