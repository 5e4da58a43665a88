"""Free-run validation: simulate a test record from θ̂ and score it, and the output-error reference.

An estimate of θ is judged, as the nonlinear benchmarks judge every model, by a **free-run
simulation** of records it was not fitted on: the model (1) with y = C x, integrated from an
initial state with the record's inputs only, compared with the measured outputs.

* the free run itself is :func:`thetahat.studies.free_run.simulate_output`: the model (1) with θ,
  the input reconstructed between samples by a ``hold`` ("zoh", "foh", "smooth" or
  "bandlimited"), integrated by RK4 sub-steps until converged.
* :func:`validate_free_run` scores θ on segments of a record: on each, x(0) is fitted to the
  first ``init_window`` samples (the benchmarks' state-initialisation window; 0: x̂(0) from
  y(0) alone), the segment is simulated from it, and the RMS error and the fit
  100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖) % are taken over the rest of the segment.
* :func:`fit_output_error` is the reference every estimator is compared with: the least-squares
  fit of (x(0), θ) to one record's outputs by that same simulation (the model taken as exact,
  θ kept in Θ's bounding box), Gauss–Newton with the exact sensitivities of the RK4 map.

What it may import: the model, :mod:`thetahat.studies.free_run`, the estimation wing's
statistical helpers, the package's validation and errors.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_samples, as_vector
from ..errors import DimensionError, OptionError, ParameterSetError
from ..estimation.hold import DEFAULT_HOLD
from ..estimation.statistical.common import theta_box
from ..model.system import PerturbedLinearSystem
from .free_run import DEFAULT_RTOL, FIRST_SUBSTEPS, FreeRun
from .metrics import rmse

__all__ = ["FreeRunValidation", "OutputErrorFit", "SegmentScore", "fit_output_error",
           "validate_free_run"]

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
# Scores on segments of a record
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True, eq=False)
class SegmentScore:
    """θ's free run on one segment of a record.

    Attributes
    ----------
    name : str
    start, stop : int
        The segment: samples [start, stop) of the record (0-based, half-open).
    init_window : int
        Its first samples, from which x(0) was fitted; not scored.
    rms : ndarray, shape (r,)
        RMS of y − ŷ over the scored samples, in the outputs' units.
    fit_percent : ndarray, shape (r,)
        100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖) over the scored samples (100: exact; 0: no better than
        the mean).
    x0 : ndarray, shape (n,)
        x(0) the simulation started from.
    substeps : int
        RK4 steps per sample interval.
    y_sim : ndarray, shape (stop − start, r)
        ŷ over the whole segment.
    """

    name: str
    start: int
    stop: int
    init_window: int
    rms: FloatArray
    fit_percent: FloatArray
    x0: FloatArray
    substeps: int
    y_sim: FloatArray

    def __repr__(self) -> str:
        return (f"SegmentScore({self.name!r}: [{self.start}, {self.stop}), "
                f"rms={np.array2string(self.rms, precision=4)}, "
                f"fit={np.array2string(self.fit_percent, precision=2)} %)")


@dataclass(frozen=True, slots=True, eq=False)
class FreeRunValidation:
    """θ's free-run simulation scored on segments of a record (:func:`validate_free_run`).

    Attributes
    ----------
    theta : ndarray, shape (p,)
    hold : str
        The input's reconstruction between samples.
    scores : tuple of SegmentScore
        One per segment, in the order given.
    """

    theta: FloatArray
    hold: str
    scores: tuple[SegmentScore, ...]

    def __getitem__(self, name: str) -> SegmentScore:
        """The score of a segment by name."""
        for s in self.scores:
            if s.name == name:
                return s
        raise OptionError(f"no segment {name!r}; the segments are "
                          f"{[s.name for s in self.scores]}.")

    def table(self, *, scale: float = 1.0, unit: str = "") -> str:
        """One line per segment and output: RMS (× ``scale``, in ``unit``) and fit %.

        Parameters
        ----------
        scale : float
            Factor applied to the RMS (1e3 for mV from V).
        unit : str

        Returns
        -------
        str
        """
        lines = [f"{'segment':<28}{'samples':>18}{'RMS ' + unit:>14}{'fit':>10}"]
        for s in self.scores:
            for i in range(s.rms.size):
                name = s.name if s.rms.size == 1 else f"{s.name} (y{i + 1})"
                lines.append(f"{name:<28}{f'[{s.start}, {s.stop})':>18}"
                             f"{scale * s.rms[i]:>14.4g}{s.fit_percent[i]:>9.2f}%")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"FreeRunValidation(hold={self.hold!r}, scores={list(self.scores)!r})"


def _fit_x0(rec: FreeRun, theta: FloatArray, y: FloatArray, x0: FloatArray, window: int,
            substeps: int) -> FloatArray:
    """x(0) minimising ‖y − ŷ‖ over the first ``window`` samples (Gauss–Newton, θ fixed)."""
    from scipy.optimize import least_squares
    ok = np.isfinite(y[:window])

    def resid(x: FloatArray) -> FloatArray:
        Y = rec.run(theta, np.ascontiguousarray(x), substeps, want=False, stop=window)[0]
        return (Y - y[:window])[ok]

    def jac(x: FloatArray) -> FloatArray:
        SX = rec.run(theta, np.ascontiguousarray(x), substeps, want=True, stop=window)[1]
        return SX[ok]

    fit = least_squares(resid, x0, jac=jac, method="lm")
    return np.ascontiguousarray(fit.x)


def _score(y: FloatArray, y_sim: FloatArray) -> tuple[FloatArray, FloatArray]:
    """RMS of y − ŷ and the fit 100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖) per output, NaN samples left out
    (NaN where an output has no sample; −inf fit for a constant y)."""
    r = y.shape[1]
    err_rms, fit = np.full(r, np.nan), np.full(r, np.nan)
    for i in range(r):
        ok = np.isfinite(y[:, i])
        if not ok.any():
            continue
        yi, si = y[ok, i], y_sim[ok, i]
        err_rms[i] = rmse(si, yi)[0]
        spread = float(np.linalg.norm(yi - yi.mean()))
        fit[i] = (100.0 * (1.0 - float(np.linalg.norm(yi - si)) / spread) if spread > 0
                  else -np.inf)
    return err_rms, fit


def _segments(segments: Mapping[str, tuple[int, int]] | None, N: int
              ) -> list[tuple[str, int, int]]:
    if segments is None:
        return [("record", 0, N)]
    out = []
    for name, bounds in segments.items():
        try:
            start, stop = (int(b) for b in bounds)
        except (TypeError, ValueError) as exc:
            raise OptionError(f"segment {name!r}: expected (start, stop); got "
                              f"{bounds!r}.") from exc
        if not 0 <= start < stop <= N or stop - start < 2:
            raise OptionError(f"segment {name!r} = [{start}, {stop}): expected "
                              f"0 <= start < stop <= {N} (the record's samples) and at least "
                              f"two samples.")
        out.append((str(name), start, stop))
    return out


def validate_free_run(system: PerturbedLinearSystem, theta: ArrayLike, t: ArrayLike,
                      u: ArrayLike | None, y: ArrayLike,
                      segments: Mapping[str, tuple[int, int]] | None = None, *,
                      hold: str = DEFAULT_HOLD, init_window: int = 0, substeps: int | None = None,
                      rtol: float = DEFAULT_RTOL,
                      compiled: bool | None = None) -> FreeRunValidation:
    """Score θ by free-run simulations of segments of a record (the benchmarks' protocol).

    On each segment: x(0) from its first ``init_window`` samples (least squares of y − ŷ over
    the window with θ fixed, started from x̂₀ = C⁺ y(0); with ``init_window = 0``, x̂₀ itself),
    the segment simulated from x(0) with its inputs (:func:`simulate_output`), and the error
    taken over the samples after the window: its RMS and the fit
    100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖) %. NaN outputs (dropouts) are left out of both.

    Parameters
    ----------
    system : PerturbedLinearSystem
    theta : array_like, shape (p,)
    t : array_like, shape (N,)
    u : array_like, shape (N, m), or None when m = 0
    y : array_like, shape (N, r)
        The measured outputs, in the model's units.
    segments : mapping of str to (start, stop), optional
        Named segments [start, stop) of the record (0-based, half-open), e.g. a model file's
        ``[data.segments]``; default: the whole record as one segment, "record".
    hold : {"zoh", "foh", "bandlimited", "smooth"}
    init_window : int
        Samples at each segment's start used to fit x(0) and not scored (the Silverbox
        benchmark's protocol: 50).
    substeps : int, optional
        RK4 steps per sample; default: converged on each segment
        (:func:`converged_substeps`).
    rtol : float
    compiled : bool, optional

    Returns
    -------
    FreeRunValidation

    Raises
    ------
    OptionError
        A segment outside the record or shorter than the window plus one sample; unknown hold.
    NonFiniteError
        The simulation diverges.
    DimensionError
        Shapes.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.studies.free_run import simulate_output
    >>> from thetahat.studies.validation import validate_free_run
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 20.0, 0.05)
    >>> u = np.sin(0.7 * t)[:, None]
    >>> y = simulate_output(spec.system, [0.5], t, u, x0=[0.2, 0.0], compiled=False)
    >>> check = validate_free_run(spec.system, [0.5], t, u, y, {"late": (100, 400)},
    ...                           init_window=20, compiled=False)
    >>> bool(check["late"].rms[0] < 1e-6), bool(check["late"].fit_percent[0] > 99.9)
    (True, True)
    """
    rec = FreeRun.of(system, t, u, hold, compiled)
    th = np.ascontiguousarray(as_vector("theta", theta, system.p))
    Y = as_samples("y", y).reshape(rec.t.size, -1)
    if Y.shape[1] != system.r:
        raise DimensionError(f"y: expected {system.r} output column(s); got {Y.shape[1]}.")
    window = int(init_window)
    if window < 0:
        raise OptionError(f"init_window: expected an integer >= 0; got {init_window!r}.")
    scores = []
    for name, start, stop in _segments(segments, rec.t.size):
        if stop - start <= window:
            raise OptionError(f"segment {name!r} = [{start}, {stop}) has no sample after its "
                              f"init_window of {window}.")
        seg = rec.segment(start, stop)
        ys = Y[start:stop]
        first = ys[0] if np.all(np.isfinite(ys[0])) else np.zeros(system.r)
        x0, *_ = np.linalg.lstsq(system.C, first, rcond=None)
        x0 = np.ascontiguousarray(x0)
        if window >= system.n:
            S0 = substeps if substeps is not None else FIRST_SUBSTEPS * 4
            x0 = _fit_x0(seg, th, ys, x0, window, S0)
        S = seg.converged(th, x0, float(rtol)) if substeps is None else substeps
        y_sim = seg.run(th, x0, S, want=False)[0]
        rms, fit = _score(ys[window:], y_sim[window:])
        y_sim.setflags(write=False)
        scores.append(SegmentScore(name=name, start=start, stop=stop, init_window=window,
                                   rms=rms, fit_percent=fit, x0=x0, substeps=int(S),
                                   y_sim=y_sim))
    th.setflags(write=False)
    return FreeRunValidation(theta=th, hold=hold, scores=tuple(scores))


# ---------------------------------------------------------------------------------------------
# The output-error reference
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True, eq=False)
class OutputErrorFit:
    """The least-squares fit of (x(0), θ) to a record by free-run simulation.

    Attributes
    ----------
    theta : ndarray, shape (p,)
    theta_sd : ndarray, shape (p,)
        The output-error Cramér–Rao standard deviation at θ̂: the square roots of the
        diagonal of σ̂² (JᵀJ)⁻¹'s θ block, J the sensitivities of the residuals to (x(0), θ)
        and σ̂ the RMS of the residuals (white noise assumed; inf where J is singular).
    x0 : ndarray, shape (n,)
    rms : ndarray, shape (r,)
        RMS of y − ŷ on the record fitted.
    hold : str
    substeps : int
        RK4 steps per sample (converged at θ̂).
    nfev : int
        Simulations the optimiser ran.
    success : bool
        The optimiser met its tolerance.
    message : str
        The optimiser's own.
    """

    theta: FloatArray
    theta_sd: FloatArray
    x0: FloatArray
    rms: FloatArray
    hold: str
    substeps: int
    nfev: int
    success: bool
    message: str

    def __repr__(self) -> str:
        return (f"OutputErrorFit(theta={self.theta.tolist()}, sd={self.theta_sd.tolist()}, "
                f"rms={self.rms.tolist()}, "
                f"hold={self.hold!r}, substeps={self.substeps}, success={self.success})")


def _oe_solve(rec: FreeRun, Y: FloatArray, q0: FloatArray, lower: FloatArray,
              upper: FloatArray, n: int, S: int, max_nfev: int) -> Any:
    """One trust-region least-squares fit of q = (x(0), θ) with S sub-steps."""
    from scipy.optimize import least_squares
    ok = np.isfinite(Y)
    memo: dict[bytes, tuple[FloatArray, FloatArray]] = {}

    def run(q: FloatArray) -> tuple[FloatArray, FloatArray]:
        key = q.tobytes()
        if key not in memo:
            memo.clear()
            Yh, SX, ST = rec.run(np.ascontiguousarray(q[n:]), np.ascontiguousarray(q[:n]), S,
                                 want=True)
            memo[key] = ((Yh - Y)[ok], np.concatenate([SX, ST], axis=2)[ok])
        return memo[key]

    lo = np.concatenate([np.full(n, -np.inf), lower])
    hi = np.concatenate([np.full(n, np.inf), upper])
    return least_squares(lambda q: run(q)[0], np.clip(q0, lo, hi), jac=lambda q: run(q)[1],
                         bounds=(lo, hi), x_scale="jac", method="trf", max_nfev=max_nfev)


def fit_output_error(system: PerturbedLinearSystem, t: ArrayLike, u: ArrayLike | None,
                     y: ArrayLike, *, theta0: ArrayLike, x0: ArrayLike | None = None,
                     hold: str = DEFAULT_HOLD, substeps: int | None = None,
                     rtol: float = DEFAULT_RTOL, max_nfev: int = 100,
                     compiled: bool | None = None) -> OutputErrorFit:
    """The output-error fit: (x(0), θ) minimising ‖y − ŷ‖ over a record, θ in Θ's box.

    The reference an estimator of θ is measured against on real data: the best free-run fit
    the model makes of the record under the same input reconstruction, with a converged
    simulator. Trust-region least squares (``scipy.optimize.least_squares``, ``trf``) with
    the exact sensitivities of the RK4 map, θ within Θ's bounding box
    (:func:`~thetahat.estimation.statistical.common.theta_box`). The sub-steps are converged at
    θ₀ and checked again at θ̂ (refitted once with more if they changed).

    Parameters
    ----------
    system : PerturbedLinearSystem
    t, u, y : array_like
        The record, as for :func:`validate_free_run`.
    theta0 : array_like, shape (p,)
        The starting θ (in Θ's box).
    x0 : array_like, shape (n,), optional
        The starting x(0) (default C⁺ y(0)).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
    substeps : int, optional
        Fixed sub-steps (default: converged).
    rtol : float
    max_nfev : int
        Iterations of the optimiser (each one simulation with sensitivities).
    compiled : bool, optional

    Returns
    -------
    OutputErrorFit

    Raises
    ------
    ParameterSetError
        θ̂ is outside Θ (Θ not a box: its bounding box let the fit out).
    NonFiniteError
        The simulation diverges at θ₀.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.studies.free_run import simulate_output
    >>> from thetahat.studies.validation import fit_output_error
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 20.0, 0.05)
    >>> u = np.sin(0.7 * t)[:, None]
    >>> y = simulate_output(spec.system, [0.8], t, u, x0=[0.0, 0.0], compiled=False)
    >>> fit = fit_output_error(spec.system, t, u, y, theta0=[0.2], compiled=False)
    >>> round(float(fit.theta[0]), 4)
    0.8
    """
    rec = FreeRun.of(system, t, u, hold, compiled)
    Y = as_samples("y", y).reshape(rec.t.size, -1)
    if Y.shape[1] != system.r:
        raise DimensionError(f"y: expected {system.r} output column(s); got {Y.shape[1]}.")
    lower, upper = theta_box(system)
    th0 = np.clip(as_vector("theta0", theta0, system.p), lower, upper)
    first = Y[0] if np.all(np.isfinite(Y[0])) else np.zeros(system.r)
    x_start = (np.linalg.lstsq(system.C, first, rcond=None)[0] if x0 is None
               else as_vector("x0", x0, system.n))
    n = system.n
    S = (rec.converged(th0, np.ascontiguousarray(x_start), float(rtol)) if substeps is None
         else int(substeps))
    fit = _oe_solve(rec, Y, np.concatenate([x_start, th0]), lower, upper, n, S, max_nfev)
    nfev = int(fit.nfev)
    if substeps is None:
        S_hat = rec.converged(np.ascontiguousarray(fit.x[n:]),
                              np.ascontiguousarray(fit.x[:n]), float(rtol))
        if S_hat > S:
            S = S_hat
            fit = _oe_solve(rec, Y, fit.x, lower, upper, n, S, max_nfev)
            nfev += int(fit.nfev)
    theta = np.ascontiguousarray(fit.x[n:])
    Theta = system.require_parameter_set("the output-error fit")
    if not Theta.contains(theta, tol=1e-9):
        raise ParameterSetError(f"the output-error fit left Θ (θ̂ = {theta.tolist()}): Θ is "
                                f"not a box, and the fit is bounded by its bounding box only.")
    Yh = rec.run(theta, np.ascontiguousarray(fit.x[:n]), S, want=False)[0]
    rms, _ = _score(Y, Yh)
    sd = _theta_sd(np.asarray(fit.jac), np.asarray(fit.fun), n)
    x_hat0 = np.array(fit.x[:n])
    for arr in (theta, sd, rms, x_hat0):
        arr.setflags(write=False)
    return OutputErrorFit(theta=theta, theta_sd=sd, x0=x_hat0, rms=rms, hold=hold,
                          substeps=S, nfev=nfev, success=bool(fit.success),
                          message=str(fit.message))


def _theta_sd(J: FloatArray, resid: FloatArray, n: int) -> FloatArray:
    """√diag(σ̂² (JᵀJ)⁻¹) of the θ block (inf where JᵀJ is singular)."""
    sigma2 = float(np.mean(resid ** 2)) if resid.size else 0.0
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Js = J / scale
    try:
        cov = np.linalg.inv(Js.T @ Js) / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        return np.full(J.shape[1] - n, np.inf)
    return np.sqrt(np.clip(np.diag(cov)[n:], 0.0, None) * sigma2)
