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
    statistical methods take u linear between samples corrected for a smooth input (their
    ``"smooth"``). ``"zoh"`` or ``"foh"`` is every method's. ``"smooth"`` and
    ``"bandlimited"`` (:mod:`thetahat.estimation.hold`) reach the statistical methods (the
    trust report of every method included); the observer (the paper's, or the guarded
    estimator's stage 1) then takes ``"foh"`` through the raw samples, except that the
    paper's method refuses ``"bandlimited"`` (its exponential integrator takes the zero- and
    first-order holds only, and its θ̂ would come from another input than the one named).

    Parameters
    ----------
    hold : {"zoh", "foh", "bandlimited", "smooth"} or None
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
    >>> split_hold("smooth", "paper")
    ('foh', 'smooth')
    """
    if hold is None:
        return "zoh", None
    h = check_hold(hold)
    if h == "smooth" or (method != "paper" and h == "bandlimited"):
        return "foh", h
    return cast(Hold, observer_hold(h)), h
