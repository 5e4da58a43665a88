"""Which hold each stage of a method takes: the one choice of ``hold`` that
:func:`~thetahat.modelfile.run_estimator`, :func:`~thetahat.modelfile.build_estimator`,
:func:`~thetahat.fleet.estimate_many` and ``thetahat estimate --hold`` share.

What it may import: the holds' checks (:mod:`thetahat.estimation.hold`, the observer's
:func:`~thetahat.estimation.observer.record_run.check_hold`).
"""

from __future__ import annotations

from typing import cast

from ..estimation.hold import check_hold
from ..estimation.observer.record_run import check_hold as observer_hold
from ..spec import Hold

__all__ = ["split_hold"]


def split_hold(hold: str | None, method: str) -> tuple[Hold, str | None]:
    """The observer's hold and the statistical methods' hold of a run's ``hold``.

    ``None`` leaves each its default: the observer holds the samples (``"zoh"``), the
    statistical methods take u linear between them (their ``"foh"``). ``"zoh"`` or ``"foh"``
    is every method's. ``"bandlimited"`` (:mod:`thetahat.estimation.hold`) reaches the
    statistical methods; the guarded estimator's stage 1 (the guard) then takes ``"foh"``,
    and the paper's observer refuses it (its exponential integrator takes the zero- and
    first-order holds only).

    Parameters
    ----------
    hold : {"zoh", "foh", "bandlimited"} or None
    method : str
        The method the run uses (:data:`thetahat.methods.ESTIMATION_METHODS`).

    Returns
    -------
    (str, str or None)
        The observer's ``"zoh"`` or ``"foh"``; the statistical methods' hold (None: theirs).

    Raises
    ------
    OptionError
        An unknown hold, or ``"bandlimited"`` with the paper's method.

    Examples
    --------
    >>> from thetahat.modelfile.holds import split_hold
    >>> split_hold(None, "guarded"), split_hold("bandlimited", "mle")
    (('zoh', None), ('foh', 'bandlimited'))
    """
    if hold is None:
        return "zoh", None
    if method != "paper" and check_hold(hold) == "bandlimited":
        return "foh", "bandlimited"
    return cast(Hold, observer_hold(hold)), hold
