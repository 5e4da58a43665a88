"""One interface for every estimator: :class:`Estimator`, and one result, :class:`EstimateResult`.

The paper's observer (:class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`), its
compiled form (:class:`~thetahat.estimation.observer.compiled.CompiledObserver`), the guarded two-stage
estimator (:class:`~thetahat.estimation.statistical.guarded.GuardedEstimator`), the MAP fits
(:class:`~thetahat.estimation.statistical.mle.MapEstimator`) and the joint EKF
(:class:`~thetahat.estimation.statistical.ekf.JointEKF`) all implement

* ``init(*, x_hat0=None, theta_hat0=None) -> state`` (θ̂₀ must lie in Θ),
* ``step(state, u, y, dt) -> state`` (process the samples at the current instant, the next
  one comes ``dt`` later), and
* ``run(t, u, y, *, state0=None) -> EstimateResult`` (a logged record).

The state is an explicit value passed from call to call, never kept in the estimator. Each
estimator documents its state type and how a state from ``step`` lines up with a row of
``run``. What differs between methods lives in the result's ``diagnostics``, a frozen object
of one type per method (:class:`ObserverDiagnostics` here, ``GuardedDiagnostics``,
``MapDiagnostics`` and ``EKFDiagnostics`` in their modules). The page
``docs/estimator-protocol.md`` shows them side by side.

This module imports nothing from the estimators (they import it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from .._validate import as_vector, positive_scalar
from ..errors import DimensionError, NonFiniteError, StateError
from ..model.perturbation import EVAL_BLOCK
from ..model.system import PerturbedLinearSystem
from ..limits import MAX_SIGNAL_MAGNITUDE, MIN_SIGNAL_MAGNITUDE
from .records import Dimensions, check_magnitude, plain_sample_ok
from .status import Status, status_error

__all__ = ["Diagnostics", "EstimateResult", "Estimator", "ObserverDiagnostics", "Evidence",
           "SignalNames", "check_sample", "check_state", "check_step_length",
           "missing_samples", "phi_hat_from_model", "stream_sample"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class Diagnostics:
    """Base of the per-method diagnostics of an :class:`EstimateResult` (no fields).

    Each estimator has one final subclass: :class:`ObserverDiagnostics`,
    :class:`~thetahat.estimation.statistical.guarded.GuardedDiagnostics`,
    :class:`~thetahat.estimation.statistical.mle.MapDiagnostics`,
    :class:`~thetahat.estimation.statistical.ekf.EKFDiagnostics`.
    """


@dataclass(frozen=True, slots=True, eq=False)
class ObserverDiagnostics(Diagnostics):
    """What the paper's observer (and its compiled form) report beyond the common estimates.

    Attributes
    ----------
    x_hat_refined : ndarray, shape (N, n), or None
        x̂₂ of the second observer of Sec. VI (None when none is attached).
    """

    x_hat_refined: FloatArray | None = None

    def __repr__(self) -> str:
        shape = None if self.x_hat_refined is None else self.x_hat_refined.shape
        return f"ObserverDiagnostics(x_hat_refined={shape})"


@dataclass(frozen=True, slots=True)
class SignalNames:
    """The names of a result's columns, as the model (file) gives them.

    Attributes
    ----------
    states, parameters, inputs, outputs : tuple of str
        One name per state, parameter, input and output.

    Examples
    --------
    >>> SignalNames(states=("omega", "eta"), parameters=("theta",), inputs=("u",),
    ...             outputs=("y",)).parameters
    ('theta',)
    """

    states: tuple[str, ...]
    parameters: tuple[str, ...]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


@runtime_checkable
class Evidence(Protocol):
    """What a result says about itself: the type of :attr:`EstimateResult.trust`.

    Implemented by :class:`~thetahat.estimation.statistical.trust.TrustReport`; declared here so
    that the result type depends on no estimator.
    """

    @property
    def warnings(self) -> tuple[str, ...]:
        """The findings that make the result less than trustworthy, one sentence each."""
        ...

    def lines(self) -> list[str]:
        """The report as lines of a summary."""
        ...

    @property
    def crlb_sd(self) -> NDArray[np.float64]:
        """The Cramér–Rao standard deviation of each parameter on the record."""
        ...


@dataclass(frozen=True, slots=True, eq=False)
class EstimateResult:
    """Estimates over a sampled record: what every :class:`Estimator`'s ``run`` returns.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sampling instants.
    x_hat : ndarray, shape (N, n)
        State estimate x̂ (the observer's (3a); stage 2's x̂ for the guarded estimator; the
        model's prediction from the latest fit for the MAP fits; the EKF's x̂).
    theta_hat : ndarray, shape (N, p)
        Parameter estimate θ̂, in Θ at every sample.
    phi_hat : ndarray, shape (N, k)
        Perturbation estimate: the observer's φ̂ = g(v, x̂, θ̂) + z of (3c); for the other
        methods φ̂ = g(v, x̂, θ̂) (:func:`phi_hat_from_model`).
    skipped : ndarray of bool, shape (N,)
        Samples whose y held NaN (no output correction was made there).
    diagnostics : Diagnostics
        Per-method extras (e.g. ``result.diagnostics.resets`` of the guarded estimator).
    status : Status
        How the run ended (:class:`~thetahat.estimation.status.Status`): ``OK``, or, for a run
        with ``throw=False`` that stopped, why (the rows from ``failed_at`` on are then NaN).
    message : str
        The sentence that says where the run stopped, why and what to do ("" when OK).
    failed_at : int or None
        The first sample the run could not process (None when OK).
    names : SignalNames or None
        The names of the states, parameters, inputs and outputs, when the model has them.
    trust : TrustReport or None
        What the estimate says about itself (:func:`~thetahat.estimation.statistical.trust.trust_report`:
        identifiability, Θ's boundary, the guard, the model error), when it was checked
        (:func:`~thetahat.modelfile.run_estimator` checks by default).

    Notes
    -----
    The arrays are read-only. ``x_hat_refined`` reads the second observer's x̂₂ from an
    :class:`ObserverDiagnostics` (None for every other method), so the tables, the CSV writer
    and the plots read any method's result the same way.
    """

    t: FloatArray
    x_hat: FloatArray
    theta_hat: FloatArray
    phi_hat: FloatArray
    skipped: NDArray[np.bool_]
    diagnostics: Diagnostics
    trust: Evidence | None = None
    status: Status = Status.OK
    message: str = ""
    failed_at: int | None = None
    names: SignalNames | None = None

    def __post_init__(self) -> None:
        for a in (self.t, self.x_hat, self.theta_hat, self.phi_hat, self.skipped):
            if a.flags.writeable:
                a.setflags(write=False)

    @property
    def ok(self) -> bool:
        """The run processed every sample (``status`` is ``OK``)."""
        return self.status == Status.OK

    def raise_for_status(self) -> EstimateResult:
        """This result if its run ended well, else the run's error (with its fix) raised.

        Returns
        -------
        EstimateResult
            ``self``.

        Raises
        ------
        ThetahatError
            :func:`~thetahat.estimation.status.status_error` of ``status`` and ``message``.
        """
        if self.status != Status.OK:
            raise status_error(self.status, self.message)
        return self

    @property
    def x_hat_refined(self) -> FloatArray | None:
        """x̂₂ of the second observer (Sec. VI), shape (N, n), or None."""
        d = self.diagnostics
        return d.x_hat_refined if isinstance(d, ObserverDiagnostics) else None

    def __repr__(self) -> str:
        N = self.t.shape[0]
        span = f"[{self.t[0]:.6g}, {self.t[-1]:.6g}]" if N else "[]"
        return (f"EstimateResult(N={N}, t={span}, x_hat={self.x_hat.shape}, "
                f"theta_hat={self.theta_hat.shape}, phi_hat={self.phi_hat.shape}, "
                f"skipped={int(self.skipped.sum())}, "
                + ("" if self.ok else f"status={self.status.name}, failed_at={self.failed_at}, ")
                + f"diagnostics={self.diagnostics!r})")

    def to_dataframe(self, *, state_names: Any = None, parameter_names: Any = None) -> Any:
        """A :class:`pandas.DataFrame` indexed by t (:func:`thetahat.tables.result_to_dataframe`).

        Parameters
        ----------
        state_names, parameter_names : sequence of str, optional
            Column suffixes (default 1, 2, …).
        """
        from ..tables import result_to_dataframe
        return result_to_dataframe(self, state_names=state_names,
                                   parameter_names=parameter_names)

    def to_xarray(self, *, state_names: Any = None, parameter_names: Any = None) -> Any:
        """An :class:`xarray.Dataset` over t (:func:`thetahat.tables.result_to_xarray`).

        Parameters
        ----------
        state_names, parameter_names : sequence of str, optional
            Coordinate labels (default 1, 2, …).
        """
        from ..tables import result_to_xarray
        return result_to_xarray(self, state_names=state_names,
                                parameter_names=parameter_names)


@runtime_checkable
class Estimator(Protocol):
    """What every estimator offers: ``init``, ``step`` and ``run`` over one explicit state.

    Implemented by :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`,
    :class:`~thetahat.estimation.observer.compiled.CompiledObserver`,
    :class:`~thetahat.estimation.statistical.guarded.GuardedEstimator`,
    :class:`~thetahat.estimation.statistical.mle.MapEstimator` and
    :class:`~thetahat.estimation.statistical.ekf.JointEKF`. ``isinstance(e, Estimator)`` checks that
    the three methods exist (Python checks no signatures at run time; mypy does).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.protocol import Estimator
    >>> obs = lugre.observer()
    >>> isinstance(obs, Estimator)
    True
    >>> data = lugre.simulate(seed=0, t_end=0.1)
    >>> res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=[0.5]))
    >>> res.theta_hat.shape, type(res.diagnostics).__name__
    ((101, 1), 'ObserverDiagnostics')
    """

    def init(self, *, x_hat0: Any = None, theta_hat0: Any = None) -> Any:
        """The state at the first sample, from x̂₀ and θ̂₀ (θ̂₀ in Θ; defaults per method)."""
        ...

    def step(self, state: Any, u: Any, y: Any, dt: float) -> Any:
        """The next state after the samples (u, y) of the current instant; ``dt`` > 0 to the
        next sample."""
        ...

    def run(self, t: Any, u: Any, y: Any, *, state0: Any = None,
            throw: bool = True) -> EstimateResult:
        """Estimates over a record (t (N,), u (N, m), y (N, r)) from ``state0`` (default
        ``init()``); a run that cannot go on raises its error (``throw=True``) or returns
        its status, message and NaN rows from ``failed_at`` on (``throw=False``)."""
        ...


def check_sample(dims: Dimensions, u: Any, y: Any) -> tuple[FloatArray, FloatArray]:
    """The samples of one instant checked: own float64 copies of u (m,) and y (r,).

    The one definition of what ``step`` accepts, for every estimator: the shapes of the
    model, u finite, y finite or NaN (a missing sample; what that means is the estimator's
    NaN policy), and the magnitudes of
    :func:`~thetahat.estimation.records.check_magnitude`.

    Parameters
    ----------
    dims : Dimensions
        Gives m and r (a :class:`~thetahat.model.system.PerturbedLinearSystem` or an
        observer's layout).
    u : array_like (m,)
        ``None`` when m = 0.
    y : array_like (r,)

    Returns
    -------
    u, y : ndarray, shapes (m,), (r,)
        Writable copies (one array type for the compiled kernels).

    Raises
    ------
    DimensionError
        Not numbers, or the wrong shapes.
    NonFiniteError
        NaN or inf in u, or inf in y.
    InputLimitError
        A magnitude float64 arithmetic of a model cannot take (rescale the unit).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> u, y = check_sample(lugre.system(), [1.0], [float("nan")])
    >>> u.shape, y.shape
    ((1,), (1,))
    """
    m, r = dims.m, dims.r
    # fast path (a stream's samples): float64 vectors of the model's sizes whose values pass
    # at once; anything else, or a value that does not, takes the checks below
    if (type(y) is np.ndarray and y.dtype == np.float64 and y.shape == (r,)
            and (u is None and m == 0 or type(u) is np.ndarray and u.dtype == np.float64
                 and u.shape == (m,))):
        if (plain_sample_ok(y.tolist(), missing=True)
                and (u is None or plain_sample_ok(u.tolist(), missing=False))):
            return (np.zeros(0) if u is None else u.copy()), y.copy()
    if y is None or (u is None and m > 0):
        which = "y" if y is None else "u"
        raise DimensionError(f"{which} must be a sample ({r if which == 'y' else m} values); "
                             f"got None.")
    u_ = np.zeros(0) if u is None else np.array(as_vector("u", u, m, finite=False))
    y_ = np.array(as_vector("y", y, r, finite=False))
    if not np.all(np.isfinite(u_)):
        raise NonFiniteError("u contains NaN or inf; clean the input sample.")
    if np.isinf(y_).any():
        raise NonFiniteError("y contains inf; only NaN marks a missing sample.")
    check_magnitude("u", u_)
    check_magnitude("y", y_)
    return u_, y_


def check_step_length(dt: Any) -> float:
    """``dt`` as a float: a real number, finite, > 0 and within the magnitudes of
    :func:`~thetahat.estimation.records.check_magnitude` (the one definition of a step length
    for every estimator's ``step``).

    Parameters
    ----------
    dt : float

    Returns
    -------
    float

    Raises
    ------
    DimensionError
        Not a real number, or ≤ 0.
    NonFiniteError
        NaN or inf.
    InputLimitError
        Below 1e-150 s or above 1e150 s (rescale the time unit).

    Examples
    --------
    >>> check_step_length(1e-3)
    0.001
    """
    if isinstance(dt, float) and MIN_SIGNAL_MAGNITUDE <= dt <= MAX_SIGNAL_MAGNITUDE:
        return float(dt)                    # fast path: what the checks below accept
    h = positive_scalar("dt", dt)
    check_magnitude("dt", [h])
    return h


def stream_sample(dims: Dimensions, u: Any, y: Any,
                  dt: Any) -> tuple[FloatArray, FloatArray, float]:
    """The samples of one ``step`` and its step length, checked: :func:`check_sample` and
    :func:`check_step_length`.

    Parameters
    ----------
    dims : Dimensions
        Gives m and r.
    u : array_like (m,)
        ``None`` when m = 0; must be finite.
    y : array_like (r,)
        NaN marks a missing sample; inf is refused.
    dt : float
        Time to the next sample, finite and > 0.

    Returns
    -------
    u, y : ndarray, shapes (m,), (r,)
        Writable copies (one array type for the compiled kernels).
    dt : float

    Raises
    ------
    DimensionError
        Wrong shapes, or dt not a real number > 0.
    NonFiniteError
        NaN or inf in u, inf in y, or dt not finite.
    InputLimitError
        A magnitude float64 arithmetic of a model cannot take.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> u, y, h = stream_sample(lugre.system(), [1.0], [float("nan")], 1e-3)
    >>> u.shape, y.shape, h
    ((1,), (1,), 0.001)
    """
    u_, y_ = check_sample(dims, u, y)
    return u_, y_, check_step_length(dt)


def _describe(state: Any) -> str:
    """What a state that was refused is, for a message."""
    if state is None:
        return "None"
    shape = getattr(state, "shape", None)
    return type(state).__name__ + ("" if shape is None else f" of shape {shape}")


def check_state(who: str, state: Any, kind: type | None,
                shapes: dict[str, tuple[int, ...]]) -> Any:
    """A state handed to ``who``'s ``step`` or ``run``, checked to be one it can continue.

    The one definition for every estimator. A state belongs to a *model*, not to an estimator
    instance: any estimator of the same model (the same dimensions) continues it, as it would
    continue from explicit start values. What a state of another model with the same
    dimensions holds cannot be told from its numbers; a stream (the guarded and MAP
    estimators' shared log) is checked further by its estimator.

    Parameters
    ----------
    who : str
        The estimator, for the message ("JointEKF.step").
    state : object
    kind : type or None
        The state's class; None: a state that is a float vector (the observers').
    shapes : dict
        Attribute → shape the model gives it (None attributes are not checked); for a vector
        state, ``{"state": (size,)}``.

    Returns
    -------
    object
        ``state``; for a vector state, a float64 vector.

    Raises
    ------
    StateError
        Another type, or another model's dimensions; the message says to start from
        ``init()``.

    Examples
    --------
    >>> check_state("obs.step", [0.0, 1.0], None, {"state": (2,)}).tolist()
    [0.0, 1.0]
    >>> check_state("obs.step", None, None, {"state": (2,)})
    Traceback (most recent call last):
    ...
    thetahat.errors.StateError: obs.step: the state must be a float vector of length 2 ...
    """
    fix = f"pass a state from {who.split('.')[0]}.init() or .step() of this model"
    if kind is None:
        (size,) = shapes["state"]
        if type(state) is np.ndarray and state.dtype == np.float64 and state.shape == (size,):
            return state                    # fast path: what as_vector returns for it
        try:
            if state is None or isinstance(state, (str, bytes)):
                raise DimensionError("not numbers")
            return as_vector("state", state, size, finite=False)
        except DimensionError as exc:
            raise StateError(f"{who}: the state must be a float vector of length {size} (this "
                             f"model's); got {_describe(state)} ({exc}). {fix[0].upper()}"
                             f"{fix[1:]}.") from exc
    if not isinstance(state, kind):
        raise StateError(f"{who}: the state must be of type {kind.__name__}; got "
                         f"{_describe(state)}. "
                         f"{fix[0].upper()}{fix[1:]}.")
    for name, shape in shapes.items():
        value = getattr(state, name, None)
        if value is None:
            continue
        if (value.shape if type(value) is np.ndarray else np.shape(value)) != shape:
            raise StateError(f"{who}: the state's {name} has shape {np.shape(value)}, this "
                             f"model's {shape}: the state was made for another model. "
                             f"{fix[0].upper()}{fix[1:]}.")
    return state


def missing_samples(Y: FloatArray) -> NDArray[np.bool_]:
    """Rows of ``Y`` (N, r) holding a NaN: the samples without output correction.

    Parameters
    ----------
    Y : ndarray, shape (N, r)

    Returns
    -------
    ndarray of bool, shape (N,)

    Examples
    --------
    >>> import numpy as np
    >>> missing_samples(np.array([[1.0], [np.nan], [2.0]])).tolist()
    [False, True, False]
    """
    return np.asarray(~np.isfinite(Y).all(axis=1), dtype=bool)


def phi_hat_from_model(system: PerturbedLinearSystem, U: FloatArray, Y: FloatArray,
                       X: FloatArray, TH: FloatArray) -> FloatArray:
    """φ̂ = g(v, x̂, θ̂) per sample, v = col(u, y), with y replaced by C x̂ where it is missing.

    The perturbation estimate of the methods that estimate (x, θ) but no φ of their own
    (guarded, MAP, EKF); the observer's φ̂ (3c) adds its z.

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a perturbation g.
    U : ndarray, shape (N, m)
    Y : ndarray, shape (N, r)
        NaN marks a missing sample (g then sees the predicted output C x̂, as the observer's
        prediction does).
    X : ndarray, shape (N, n)
    TH : ndarray, shape (N, p)

    Returns
    -------
    ndarray, shape (N, k)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> sys_ = lugre.system()
    >>> phi = phi_hat_from_model(sys_, np.zeros((2, 1)), np.array([[0.0], [np.nan]]),
    ...                          np.zeros((2, 2)), np.full((2, 1), 0.28))
    >>> phi.shape, bool(np.isfinite(phi).all())
    ((2, 1), True)
    """
    pert = system.require_perturbation("phi_hat_from_model")
    N = X.shape[0]
    out = np.empty((N, system.k))
    for a in range(0, N, EVAL_BLOCK):       # v a block at a time: not a copy of the record
        rows = slice(a, a + EVAL_BLOCK)
        Yb = Y[rows]
        gone = missing_samples(Yb)
        Yc = np.where(gone[:, None], X[rows] @ system.C.T, Yb) if gone.any() else Yb
        V = np.concatenate([U[rows], Yc], axis=1)
        out[rows] = np.asarray(pert.g(V, X[rows], TH[rows]),
                               dtype=np.float64).reshape(-1, system.k)
    return out
