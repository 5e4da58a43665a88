"""What the statistical estimators share: start values, priors, σ, the sample interval, a stop.

Every module of the room that needs one of these imports it from here, so that each is
defined once: Θ's bounding box (:func:`theta_box`), the start values (x̂₀, θ̂₀) with θ̂₀ in Θ
(:func:`start_values`), the priors of θ and of x(0) (:func:`theta_prior_sd`,
:func:`x_prior_sd`) and their joint form on col(x, θ) (:func:`joint_prior`), the output
noise level (:func:`resolve_noise_std`), the sampling interval of a record
(:func:`sample_interval`), and how a run that stopped is reported (:class:`RunStop`,
:func:`stopped_result`: the one failure behaviour of
:mod:`~thetahat.estimation.status`).

What it may import: :mod:`thetahat.model`, the package's helpers (``_validate``, ``errors``),
the bottom of the estimation wing (:mod:`~thetahat.estimation.protocol`,
:mod:`~thetahat.estimation.status`), and, in this room, only
:mod:`~thetahat.estimation.statistical.noise_level` and
:mod:`~thetahat.estimation.statistical.stage2_set` (which import nothing of the room).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_vector
from ...errors import DimensionError, OptionError, ParameterSetError, ThetahatError
from ...model.system import PerturbedLinearSystem
from ..protocol import Diagnostics, EstimateResult, phi_hat_from_model
from ..status import Status, status_error
from .noise_level import MIN_SAMPLES, estimate_noise_std
from .stage2_set import theta_bounds

__all__ = ["PRIOR_FRACTION", "STEP_TOL", "X_PRIOR_SD", "RunStop", "joint_prior", "model_phi_hat",
           "resolve_noise_std",
           "sample_interval", "start_values", "stopped_result", "theta_box", "theta_prior_sd",
           "x_prior_sd"]

FloatArray = NDArray[np.float64]

#: A fit of θ has converged once the step still to go is below this many standard errors of θ
#: (the MAP fits' Gauss–Newton iteration and the likelihood fits alike).
STEP_TOL = 0.02

#: Prior standard deviation of θ as a fraction of Θ's width per component: θ's prior
#: N(centre of Θ, (|Θ|/4)²) puts Θ's ends at 2 standard deviations.
PRIOR_FRACTION = 0.25

#: Prior standard deviation of x(0) per unit of the start's magnitude max(1, max|x̂(0)ᵢ|):
#: wide against the state (the data determine x(0)), in the state's own scale where the start
#: gives one (x̂(0) from y(0), :func:`~thetahat.modelfile.start_x_hat`) — a heater started
#: 300 K above its reference is not pulled to the reference by a prior of ± 10 K.
X_PRIOR_SD = 10.0


def theta_box(system: PerturbedLinearSystem) -> tuple[FloatArray, FloatArray]:
    """(lower, upper): Θ's bounding box, Θ itself for a :class:`~thetahat.model.paramset.Box`.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model; its ``parameter_set`` Θ may be any
        :class:`~thetahat.model.paramset.ParameterSet` (Box, Ball, Ellipsoid, ConvexSet).

    Returns
    -------
    lower, upper : ndarray, shape (p,)
        Θ's extent per component of θ (:func:`~thetahat.estimation.statistical.stage2_set.theta_bounds`),
        as float64 copies: the prior's width and the guard's widest band. Stage 2 keeps θ̂ in
        Θ itself by projecting onto Θ (:mod:`~thetahat.estimation.statistical.stage2_set`), not by
        clipping to this box unless Θ is the box.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.common import theta_box
    >>> [b.tolist() for b in theta_box(lugre.system())]
    [[0.05], [1.0]]
    """
    return theta_bounds(system.require_parameter_set("stage 2"))


def start_values(system: PerturbedLinearSystem, x_hat0: ArrayLike | None = None,
                 theta_hat0: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
    """(x̂₀, θ̂₀) of the statistical estimators: defaults zeros and the centre of Θ, θ̂₀ in Θ.

    Parameters
    ----------
    system : PerturbedLinearSystem
        Any Θ; the default θ̂₀ is its ``interior_point`` (the centre of a box, ball or
        ellipsoid).
    x_hat0 : array_like (n,), optional
    theta_hat0 : array_like (p,), optional

    Returns
    -------
    x_hat0, theta_hat0 : ndarray

    Raises
    ------
    ParameterSetError
        θ̂₀ outside Θ.
    DimensionError
        Wrong lengths.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.common import start_values
    >>> start_values(lugre.system())[1]
    array([0.525])
    """
    theta_set = system.require_parameter_set("stage 2")
    x0 = (np.zeros(system.n) if x_hat0 is None
          else as_vector("x_hat0", x_hat0, system.n))
    th0 = (np.array(theta_set.interior_point, dtype=np.float64) if theta_hat0 is None
           else as_vector("theta_hat0", theta_hat0, system.p))
    if not bool(theta_set.contains(th0)):
        raise ParameterSetError(f"theta_hat0 = {th0} lies outside Θ = {theta_set!r}; start "
                                "the estimate inside Θ.")
    return x0, th0


def theta_prior_sd(system: PerturbedLinearSystem) -> FloatArray:
    """Prior standard deviation of θ from Θ: :data:`PRIOR_FRACTION` × its width.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model; any Θ (its bounding box, :func:`theta_box`, gives the width).

    Returns
    -------
    ndarray, shape (p,)
        |Θ|/4 per component: the prior N(centre of Θ, (|Θ|/4)²) of the EKF on col(x, θ) and
        of the first MAP fit puts Θ's ends at 2 standard deviations.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.common import theta_prior_sd
    >>> theta_prior_sd(lugre.system()).round(4).tolist()
    [0.2375]
    """
    lo, hi = theta_box(system)
    return PRIOR_FRACTION * (hi - lo)


def x_prior_sd(x_hat0: ArrayLike, x_sd: ArrayLike | None = None) -> FloatArray:
    """Prior standard deviation of x(0) around x̂(0): ``x_sd`` when given, else derived.

    Parameters
    ----------
    x_hat0 : array_like (n,)
        The prior mean x̂(0).
    x_sd : float or array_like (n,), optional
        Given standard deviations (used as they are). Default: :data:`X_PRIOR_SD` ×
        max(1, max|x̂(0)ᵢ|) for every component.

    Returns
    -------
    ndarray, shape (n,)
        Positive and finite.

    Raises
    ------
    OptionError
        A given ``x_sd`` that is not positive and finite.
    DimensionError
        A given ``x_sd`` that is neither a number nor one per state.

    Examples
    --------
    >>> from thetahat.estimation.statistical.common import x_prior_sd
    >>> x_prior_sd([0.2, 0.0]).tolist(), x_prior_sd([300.0, 0.0]).tolist()
    ([10.0, 10.0], [3000.0, 3000.0])
    """
    x0 = np.asarray(x_hat0, dtype=np.float64).reshape(-1)
    if x_sd is None:
        scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        return np.full(x0.shape[0], X_PRIOR_SD * scale)
    try:
        sd = np.array(np.broadcast_to(np.asarray(x_sd, dtype=np.float64), x0.shape))
    except ValueError:
        raise DimensionError(f"x_sd must be a number or have {x0.shape[0]} entries (one per "
                             f"state); got shape {np.shape(x_sd)}.") from None
    if not np.all(np.isfinite(sd) & (sd > 0.0)):
        raise OptionError(f"x_sd must be positive and finite; got {sd.tolist()}.")
    return sd


def joint_prior(system: PerturbedLinearSystem, x_hat0: ArrayLike | None = None,
                theta_hat0: ArrayLike | None = None, *, theta_sd: ArrayLike | None = None,
                x_sd: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
    """(s0, P0): the prior of the joint EKF on s = col(x, θ), its mean and covariance.

    Parameters
    ----------
    system : PerturbedLinearSystem
    x_hat0, theta_hat0 : array_like, optional
        The means (:func:`start_values`: default zeros and the centre of Θ; θ̂₀ in Θ).
    theta_sd : array_like (p,), optional
        Prior standard deviation of θ; default :func:`theta_prior_sd`.
    x_sd : float or array_like (n,), optional
        Prior standard deviation of x(0); default :func:`x_prior_sd` of x̂₀.

    Returns
    -------
    s0 : ndarray (n + p,)
        col(x̂₀, θ̂₀).
    P0 : ndarray (n + p, n + p)
        diag(x_sd², θ_sd²).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> s0, P0 = joint_prior(lugre.system(), theta_hat0=[0.5])
    >>> s0.tolist(), P0.diagonal().round(4).tolist()
    ([0.0, 0.0, 0.5], [100.0, 100.0, 0.0564])
    """
    x0, th0 = start_values(system, x_hat0, theta_hat0)
    th_sd = (theta_prior_sd(system) if theta_sd is None
             else as_vector("theta_sd", theta_sd, system.p))
    return (np.concatenate([x0, th0]),
            np.diag(np.concatenate([x_prior_sd(x0, x_sd), th_sd]) ** 2))


def sample_interval(t: FloatArray) -> float:
    """The median spacing of ``t``: the sampling interval of a uniform record (1 with < 2).

    What a per-sample covariance (process noise over one sample) and the process-noise
    scale are taken over; the median keeps a few dropped samples from moving it.

    Parameters
    ----------
    t : ndarray (N,)

    Returns
    -------
    float

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.common import sample_interval
    >>> sample_interval(np.array([0.0, 0.1, 0.2, 0.5]))
    0.1
    """
    return float(np.median(np.diff(t))) if t.shape[0] > 1 else 1.0


def resolve_noise_std(noise_std: ArrayLike | None, Y: FloatArray) -> FloatArray:
    """σ per output: as given (> 0), else estimated from the record's differences.

    Parameters
    ----------
    noise_std : float or array_like (r,), optional
        The given σ (one for every output, or one per output).
    Y : ndarray (N, r)
        The outputs σ is estimated from when not given
        (:func:`~thetahat.estimation.statistical.noise_level.estimate_noise_std`; NaN marks a
        missing sample).

    Returns
    -------
    ndarray (r,)
        Finite and > 0.

    Raises
    ------
    DimensionError
        σ not given and fewer than :data:`~thetahat.estimation.statistical.noise_level.MIN_SAMPLES`
        samples, or a σ that is not finite and > 0 (noise-free data: pass a small one).

    Examples
    --------
    >>> import numpy as np
    >>> resolve_noise_std(0.02, np.zeros((1, 2))).tolist()
    [0.02, 0.02]
    """
    r = Y.shape[1]
    if noise_std is None:
        if Y.shape[0] < MIN_SAMPLES:
            raise DimensionError(f"the output noise level σ cannot be estimated from "
                                 f"{Y.shape[0]} samples (it needs {MIN_SAMPLES}): give it "
                                 f"(noise_std=σ in Python; thetahat estimate --noise-std σ), "
                                 f"or use a record of at least {MIN_SAMPLES} samples.")
        sigma = estimate_noise_std(Y)
    else:
        try:
            sigma = np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (r,)).copy()
        except (TypeError, ValueError) as exc:
            raise DimensionError(f"noise_std (--noise-std) must be one number, or one per "
                                 f"output ({r}); got "
                                 f"{noise_std!r}.") from exc
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise DimensionError(f"the noise level must be finite and > 0; got σ = {sigma} (noise-"
                             "free data: give a small one, e.g. 1e-6 of the signal: "
                             "noise_std= in Python, --noise-std on the command line).")
    return sigma


class RunStop(NamedTuple):
    """Why and where a run stopped: the sample it could not process, its status and message.

    Attributes
    ----------
    status : Status
        :attr:`~thetahat.estimation.status.Status.DIVERGED` (a non-finite estimate) or
        :attr:`~thetahat.estimation.status.Status.SINGULAR` (a singular solve).
    message : str
        Where, what and what to do: the sentence of the error ``throw=True`` raises.
    at : int
        The first row the run could not produce (``failed_at``).

    Examples
    --------
    >>> stop = RunStop(Status.DIVERGED, "the EKF diverged at t[3] = 0.003", 3)
    >>> type(stop.error()).__name__, str(stop.error())
    ('NonFiniteError', 'the EKF diverged at t[3] = 0.003')
    """

    status: Status
    message: str
    at: int

    def error(self) -> ThetahatError:
        """The exception of ``throw=True``: :func:`~thetahat.estimation.status.status_error`.

        Returns
        -------
        ThetahatError
        """
        return status_error(self.status, self.message)


def model_phi_hat(system: PerturbedLinearSystem, U: FloatArray, Y: FloatArray, X: FloatArray,
                  TH: FloatArray, stop: RunStop | None = None) -> FloatArray:
    """φ̂ = g(v, x̂, θ̂) of a run's rows (:func:`~thetahat.estimation.protocol.phi_hat_from_model`),
    NaN from the row where the run stopped.

    Parameters
    ----------
    system : PerturbedLinearSystem
    U, Y, X, TH : ndarray, shapes (N, m), (N, r), (N, n), (N, p)
        The record and the run's estimates (rows from ``stop.at`` on are not read).
    stop : RunStop, optional
        None: every row.

    Returns
    -------
    ndarray (N, k)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> phi = model_phi_hat(lugre.system(), np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 2)),
    ...                     np.full((3, 1), 0.28), RunStop(Status.DIVERGED, "diverged", 2))
    >>> np.isnan(phi[:, 0]).tolist()
    [False, False, True]
    """
    if stop is None:
        return phi_hat_from_model(system, U, Y, X, TH)
    k = stop.at
    phi = np.full((X.shape[0], system.k), np.nan)
    phi[:k] = phi_hat_from_model(system, U[:k], Y[:k], X[:k], TH[:k])
    return phi


def stopped_result(*, t: FloatArray, x_hat: FloatArray, theta_hat: FloatArray,
                   phi_hat: FloatArray, skipped: NDArray[np.bool_], diagnostics: Diagnostics,
                   stop: RunStop | None, blank: Sequence[FloatArray] = ()) -> EstimateResult:
    """The result of a run: OK, or, when it stopped, its status, message and ``failed_at``.

    An estimate that is not finite before the run's own stop (x̂ or θ̂ overflowing, or
    φ̂ = g(v, x̂, θ̂) overflowing at finite x̂ and θ̂ — data far beyond the model's scale) stops
    the run there too, as :attr:`~thetahat.estimation.status.Status.DIVERGED`: NaN or inf
    never leaves a run unannounced. When the run stopped, the rows of ``x_hat``,
    ``theta_hat``, ``phi_hat`` and of every array in ``blank`` from ``stop.at`` on are set to
    NaN here (in place): nothing computed at or after the sample the run could not process is
    read as an estimate; the rows before are the run's.

    Parameters
    ----------
    t, x_hat, theta_hat, phi_hat, skipped, diagnostics
        As :class:`~thetahat.estimation.protocol.EstimateResult`'s.
    stop : RunStop or None
        None: the run processed every sample (status OK).
    blank : sequence of ndarray
        The diagnostics' arrays with a row per sample (blanked with the estimates).

    Returns
    -------
    EstimateResult

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.protocol import ObserverDiagnostics
    >>> X = np.ones((4, 1))
    >>> res = stopped_result(t=np.arange(4.0), x_hat=X, theta_hat=X.copy(), phi_hat=X.copy(),
    ...                      skipped=np.zeros(4, bool), diagnostics=ObserverDiagnostics(),
    ...                      stop=RunStop(Status.DIVERGED, "diverged at t[2]", 2))
    >>> res.status.name, res.failed_at, res.theta_hat[:, 0].tolist()
    ('DIVERGED', 2, [1.0, 1.0, nan, nan])
    """
    rows = t.shape[0] if stop is None else stop.at
    with np.errstate(invalid="ignore"):
        bad = ~(np.isfinite(x_hat[:rows]).all(axis=1) & np.isfinite(theta_hat[:rows]).all(axis=1)
                & np.isfinite(phi_hat[:rows]).all(axis=1))
    if bad.any():
        k = int(np.argmax(bad))
        if np.isfinite(x_hat[k]).all() and np.isfinite(theta_hat[k]).all():
            # g itself is undefined there (a division by zero, a log of a negative number)
            where = (f"φ̂ = g(v, x̂, θ̂) is not finite at t[{k}] = {float(t[k]):.6g}, at finite "
                     f"x̂ = {np.array2string(x_hat[k], precision=4)} and θ̂ = "
                     f"{np.array2string(theta_hat[k], precision=4)}: g has no finite value "
                     "there")
            advice = ("start x̂ where g is defined (x_hat0)" if k == 0 else
                      "check g's domain against the data, or rescale the units of u and y")
            stop = RunStop(Status.DIVERGED, f"{where}; {advice}.", k)
        else:
            stop = RunStop(Status.DIVERGED, f"the estimates are not finite from t[{k}] = "
                           f"{float(t[k]):.6g} on (x̂ or θ̂ overflows there): the data lie "
                           "beyond what the model's arithmetic takes (rescale the units of u "
                           "and y) or the run diverged.", k)
    if stop is None:
        return EstimateResult(t=t, x_hat=x_hat, theta_hat=theta_hat, phi_hat=phi_hat,
                              skipped=skipped, diagnostics=diagnostics)
    for a in (x_hat, theta_hat, phi_hat, *blank):
        a[stop.at:] = np.nan
    return EstimateResult(t=t, x_hat=x_hat, theta_hat=theta_hat, phi_hat=phi_hat,
                          skipped=skipped, diagnostics=diagnostics, status=stop.status,
                          message=stop.message, failed_at=stop.at)
