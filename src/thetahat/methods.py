"""The estimation methods, written once: their names, what each one is, and how it is built.

:data:`METHODS` is the one ordered list of the methods — ``"guarded"`` (the default,
:data:`DEFAULT_METHOD`), ``"paper"``, ``"mle"`` and ``"ekf"`` — each a :class:`Method` with
its one-line description and the one function that builds its
:class:`~thetahat.estimation.protocol.Estimator` from a :class:`MethodInputs`. A model file's ``[estimator] method`` (validated by :mod:`thetahat.modelfile.schema`),
:func:`thetahat.modelfile.build_estimator` and :func:`~thetahat.modelfile.run_estimator`,
:func:`thetahat.models.lugre.estimator` and ``thetahat estimate --method`` (its choices and its
help) all read it; none of them lists the names again.

What it may import: :mod:`thetahat.spec` and below (the estimators of
:mod:`thetahat.estimation`, imported when a method is built). Model files, the shipped models,
the studies and the command line import it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from .errors import OptionError, ThetahatError

if TYPE_CHECKING:       # annotations only: the command line's parser reads the names of the
    from .estimation.protocol import Estimator     # methods without loading SymPy and SciPy
    from .model.system import PerturbedLinearSystem

__all__ = ["DEFAULT_METHOD", "ESTIMATION_METHODS", "METHODS", "Method", "MethodInputs",
           "get_method", "method_help"]


@dataclass(frozen=True, slots=True, kw_only=True)
class MethodInputs:
    """What a method is built from: what a model file or a shipped model gives.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The system (1) with its g and Θ (the statistical methods' plant model).
    observer : callable
        ``observer()`` builds the paper's observer (3) with its update law (8): the
        ``"paper"`` estimator, and stage 1 of ``"guarded"`` unless ``stage1`` is given. Called
        only by the methods that run it (``"mle"`` and ``"ekf"`` never design gains).
    stage1 : callable, optional
        ``stage1()`` builds the guarded estimator's stage 1 when it is not ``observer()`` (the
        LuGre model's compiled observer for a fixed step).
    noise_std : float or array_like (r,), optional
        σ of the output noise for the statistical methods (default: estimated from the data).
    compiled : bool, optional
        numba kernels for the statistical methods (default: when installed).
    hold : {"zoh", "foh", "bandlimited", "smooth"}, optional
        u between the samples for the statistical methods (the guarded estimator's stage 2,
        the MAP fits, the joint EKF; :mod:`thetahat.estimation.hold`); default: each one's
        own (``"smooth"``). The observer's hold is in ``observer``.
    window : {None, "auto"} or int, optional
        The fitting methods' bounded fits (:mod:`~thetahat.estimation.statistical.window`):
        None fits all the data so far (the default), ``"auto"`` or W samples bound each fit.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.methods import MethodInputs, get_method
    >>> inputs = MethodInputs(system=lugre.system(), observer=lugre.observer, compiled=False)
    >>> type(get_method("guarded").build(inputs)).__name__
    'GuardedEstimator'
    >>> type(get_method("ekf").build(inputs)).__name__
    'JointEKF'
    """

    system: PerturbedLinearSystem
    observer: Callable[[], Estimator]
    stage1: Callable[[], Estimator] | None = None
    noise_std: Any = None
    compiled: bool | None = None
    hold: str | None = None
    window: int | str | None = None

    def stage2(self, fits: bool = False) -> dict[str, Any]:
        """The keywords a statistical estimator takes from these inputs (``fits``: one that
        makes MAP fits, so also the window)."""
        given: dict[str, Any] = {"noise_std": self.noise_std, "compiled": self.compiled}
        if self.hold is not None:
            given["hold"] = self.hold
        if fits and self.window is not None:
            given["window"] = self.window
        return given


@dataclass(frozen=True, slots=True)
class Method:
    """One estimation method: its name, what it is, how it is built.

    Parameters
    ----------
    name : str
        The name a model file, the API and the command line give.
    description : str
        What it is, in one line (the command line's help and the model-file reference).
    build : callable
        ``build(inputs: MethodInputs) -> Estimator``.
    runs_observer : bool
        It runs the paper's observer, so the law's θ* is checked on the record first and
        ``Gamma = "auto"`` is chosen on it (:func:`~thetahat.modelfile.run_estimator`).
    fits : bool
        Its ``run`` makes MAP fits and takes ``fit_progress``
        (:data:`thetahat.progress.FitProgress`).

    Examples
    --------
    >>> from thetahat.methods import get_method
    >>> get_method("mle").runs_observer
    False
    """

    name: str
    description: str
    build: Callable[[MethodInputs], Estimator]
    runs_observer: bool
    fits: bool = False

    def __repr__(self) -> str:
        return f"Method({self.name!r}: {self.description})"


def _paper(inputs: MethodInputs) -> Estimator:
    return inputs.observer()


def _guarded(inputs: MethodInputs) -> Estimator:
    from .estimation.statistical.guarded import GuardedEstimator
    stage1 = (inputs.observer if inputs.stage1 is None else inputs.stage1)()
    return GuardedEstimator(stage1=stage1, system=inputs.system, **inputs.stage2(fits=True))


def _mle(inputs: MethodInputs) -> Estimator:
    from .estimation.statistical.mle import MapEstimator
    return MapEstimator(system=inputs.system, **inputs.stage2(fits=True))


def _ekf(inputs: MethodInputs) -> Estimator:
    from .estimation.statistical.ekf import JointEKF
    return JointEKF(system=inputs.system, **inputs.stage2())


#: The estimation methods, in the order the command line and the docs list them; the first is
#: the default (:data:`DEFAULT_METHOD`).
METHODS: tuple[Method, ...] = (
    Method("guarded", "the two-stage guarded estimator: the paper's observer guarding an EKF "
                      "re-anchored by MAP fits (the default: guaranteed and efficient)",
           _guarded, runs_observer=True, fits=True),
    Method("paper", "the paper's observer (3) with its update law (8), as printed (its "
                    "guarantee needs the law's conditions, Props. 1-4, on the record)",
           _paper, runs_observer=True),
    Method("mle", "MAP fits of (x(0), θ) on a dense schedule (offline)", _mle,
           runs_observer=False, fits=True),
    Method("ekf", "the joint EKF on col(x, θ) alone", _ekf, runs_observer=False),
)

#: The names of :data:`METHODS`, in their order.
ESTIMATION_METHODS: tuple[str, ...] = tuple(m.name for m in METHODS)
#: The method of a model file without ``[estimator] method`` and of ``thetahat estimate``
#: without ``--method``: the guarded estimator, whose θ̂ carries stage 1's guarantee (the
#: guard) and reaches the Cramér–Rao bound (stage 2's fits). The paper's observer alone
#: converges only where its law's conditions hold on the record, which the trust report
#: checks but a newcomer cannot know beforehand.
DEFAULT_METHOD: str = METHODS[0].name


def get_method(name: str, *,
               error: Callable[[str], ThetahatError] = OptionError) -> Method:
    """The method of a name.

    Parameters
    ----------
    name : str
        One of :data:`ESTIMATION_METHODS`.
    error : callable, optional
        Makes the exception of an unknown name from its message (default
        :class:`~thetahat.errors.OptionError`; a model file names its key).

    Returns
    -------
    Method

    Raises
    ------
    OptionError
        ``name`` is no method (or what ``error`` makes); the message lists the methods.

    Examples
    --------
    >>> from thetahat.methods import get_method
    >>> get_method("ekf")
    Method('ekf': the joint EKF on col(x, θ) alone)
    >>> get_method("newton")
    Traceback (most recent call last):
    ...
    thetahat.errors.OptionError: unknown method 'newton'; expected one of ['guarded', 'paper', 'mle', 'ekf'].
    """
    for method in METHODS:
        if method.name == name:
            return method
    shown = repr(name) if len(repr(name)) <= 60 else repr(name)[:57] + "..."
    raise error(f"unknown method {shown}; expected one of {list(ESTIMATION_METHODS)}.")


def method_help() -> str:
    """The methods and what each one is, as one sentence (the command line's help).

    Returns
    -------
    str

    Examples
    --------
    >>> from thetahat.methods import method_help
    >>> method_help().split("; ")[2]
    'mle: MAP fits of (x(0), θ) on a dense schedule (offline)'
    """
    return "; ".join(f"{m.name}: {m.description}" for m in METHODS)
