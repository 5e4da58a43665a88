"""Model-file schema: reading and validating a model file into a :class:`ModelSpec`.

A model file (TOML, read with :mod:`tomllib`, or JSON with the same structure) holds:

``name`` (optional)
    A title.
``[system]``
    ``A`` (n × n), ``B`` (n × m; ``[]`` when m = 0), ``C`` (r × n), ``E`` (n × k) as nested
    lists of rows of numbers, eq. (1).
``[perturbation]``
    ``g``: φ = g(v, x, θ) as a string (k = 1) or a list of k strings, in the safe syntax of
    :func:`~thetahat.model.parse.parse_perturbation` (never evaluated as code); ``u``, ``y``,
    ``x``, ``theta``: the symbol names (lists of m, r, n and p names; a single name may be
    given as a string); ``constants`` (optional table): named numbers used in the formulas.
``[parameter_set]``
    Θ, one of three convex sets (:mod:`thetahat.model.paramset`): a box, ``lower`` and
    ``upper`` (p numbers each); a ball, ``center`` (p numbers) and ``radius`` (a number > 0),
    {θ : ‖θ − center‖ ≤ radius}; or an ellipsoid, ``center`` and ``shape`` (a p × p symmetric
    positive-definite Q), {θ : (θ − center)ᵀ Q (θ − center) ≤ 1} (each eigenvalue of Q is
    1/a² for a semi-axis a). A general convex set {P(θ) ≤ 0} needs a Python callable P and
    exists in the API only (:class:`~thetahat.model.paramset.ConvexSet`).
``[estimator]``
    ``law`` (required): ``"gradient"`` (:class:`~thetahat.estimation.observer.laws.
    GradientInversion` with the default M = (∂g/∂θ)ᵀ, Propositions 3–4), ``"least_squares"``
    (:class:`~thetahat.estimation.observer.laws.least_squares.FilteredLeastSquares`: the regressor
    filtered like φ̂, a gain Γ(t) that shrinks as information grows), ``"algebraic"``
    (:class:`~thetahat.estimation.observer.laws.AlgebraicInversion`, Proposition 1) or
    ``"intermittent"`` (:class:`~thetahat.estimation.observer.laws.IntermittentInversion`,
    Proposition 2, with the excitation weight ``smooth_ramp(*excitation)`` of ‖φ̂‖).
    Optional: ``eps`` (default 1, Sec. VII), ``chain_poles`` (one list per chain; default
    −1, −2, …), ``b_poles``, ``Gamma`` (number, p × p or ``"auto"``; default ``"auto"`` for
    the gradient and least-squares laws — :mod:`~thetahat.estimation.observer.auto_gain` — and
    1 for the inversion laws), ``theta_hat0``
    (default: the centre of Θ), ``x_hat0`` (default 0: the prior of x̂(0)), ``x_hat0_from_y``
    (default true: every method starts at x̂(0) = x̂₀ + C⁺(y(0) − C x̂₀), the state nearest
    x̂₀ that fits the record's first sample, :func:`~thetahat.estimation.observer.initial_state.
    x_hat_from_output`; false: at x̂₀), ``theta_star`` (algebraic and
    intermittent laws: θ*(v, x, φ) as a string or list of p strings, in the names of u, y, x
    and ``phi`` (k = 1) or ``phi1``, …, ``phik``; default: solved from g with SymPy),
    ``excitation`` (intermittent law, required: ``[low, high]`` thresholds on ‖φ̂‖),
    ``on_invalid`` (``"raise"`` or ``"freeze"``, default ``"raise"``), ``method``
    (``"paper"``, default: the observer and law above; ``"guarded"``: that observer as stage 1
    of :class:`~thetahat.estimation.statistical.guarded.GuardedEstimator`; ``"mle"``:
    :class:`~thetahat.estimation.statistical.mle.MapEstimator`, offline; ``"ekf"``:
    :class:`~thetahat.estimation.statistical.ekf.JointEKF`), and ``A_design``,
    ``E_design``: the matrices of a simplified design system on which the gains are designed
    (Sec. VII–VIII; default: the true A and E); ``allow_nonminimum_phase`` (default false:
    a model that violates Assumption 1 is refused; true designs anyway, to study the failure).
``[estimator.second]`` (optional)
    The second observer of Sec. VI: ``eps2`` (default 1), ``chain_poles``, ``b_poles``,
    ``g_on_estimates`` (default false; true evaluates g on C x̂₂ instead of the noisy y, as in
    Sec. VIII).
``[scenario]`` (optional)
    The simulated experiment of ``thetahat sweep`` and ``thetahat tune``
    (:func:`~thetahat.modelfile.study.simulate_model`): the true ``theta`` (default: the
    point half way from Θ's centre to its point nearest the upper corner of Θ's bounding box:
    for a box, three quarters of the way from ``lower`` to ``upper``), ``x0``
    (default 0), ``t_end`` (s, default 20), ``fs`` (Hz, default 100), ``noise_std`` (white
    noise on y, default 0.01), the input as a sum of sines per channel, ``u_amplitudes`` and
    ``u_frequencies`` (Hz) (a list of q numbers for every channel, or one list per channel;
    default 1 sin(2π·0.1 t) + 0.5 sin(2π·0.3 t)), and the integrator ``method`` (default
    ``"Radau"``), ``rtol`` (1e-8) and ``atol`` (a number or n numbers, 1e-10). The plant
    is simulated with the file's g, evaluated on the noise-free output C x.

``[data]`` (optional)
    Which variables (MATLAB files) or columns (CSV, Parquet) of a data file are ``t``, ``u``
    and ``y``, each a name or ``{ column = "NAME", scale = 1.0, offset = 0.0 }`` (value =
    scale · raw + offset), a list of m (r) signals for several inputs (outputs); ``t`` may
    instead be ``{ rate = HZ }`` when the record has no time vector. See
    :mod:`thetahat.io.mapping`.

Unknown keys are errors (they are usually typos). Every problem is reported as a
:class:`~thetahat.errors.ModelFileError` naming the file, the section and the key.

Data files for :func:`thetahat.io.datafile.read_data` are CSV with a header row, Parquet or MATLAB
(``.mat``, v4–v7) files. Without ``[data]``, they hold a column ``t`` (strictly increasing),
one column per input, named as in ``[perturbation] u`` or ``u1``, ``u2``, … (``u`` also works
when m = 1), and one per output, named as in ``[perturbation] y`` or ``y1``, … (``y`` when
r = 1). Column order is free and other columns are ignored.
"""

from __future__ import annotations

import functools
import json
import math
import sys
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import limits
from ..io.mapping import DataMapping, RecordLayout, parse_data_table
from ..errors import InputLimitError, ModelFileError, ThetahatError
from ..estimation.observer.laws.least_squares import FilteredLeastSquares
from ..estimation.observer.laws.projection import as_gain
from ..safe_io import read_text
from ..estimation.observer.laws import (
    AlgebraicInversion,
    GradientInversion,
    IntermittentInversion,
    UpdateLaw,
    smooth_ramp,
)
from ..model.paramset import Ball, Box, Ellipsoid, ParameterSet
from ..model.parse import parse_perturbation
from ..estimation.statistical.stage2_set import theta_bounds
from ..model.perturbation import SymbolicPerturbation
from ..model.system import PerturbedLinearSystem

__all__ = ["AUTO_GAMMA_LAWS", "ESTIMATION_METHODS", "EXAMPLE_MODEL", "EstimatorOptions", "LAWS", "ModelSpec",
           "SCENARIO_METHODS", "ScenarioOptions", "SecondObserverOptions", "load_model",
           "loads_model"]

FloatArray = NDArray[np.float64]

LAWS = ("gradient", "least_squares", "algebraic", "intermittent")
#: The laws whose Γ defaults to ``"auto"`` (:mod:`~thetahat.estimation.observer.auto_gain`).
AUTO_GAMMA_LAWS = ("gradient", "least_squares")
_TOP_KEYS = ("name", "system", "perturbation", "parameter_set", "estimator", "scenario",
             "data")
_SYSTEM_KEYS = ("A", "B", "C", "E")
_PERTURBATION_KEYS = ("g", "u", "y", "x", "theta", "constants")
_BOX_KEYS = ("lower", "upper")
_BALL_KEYS = ("center", "radius")
_ELLIPSOID_KEYS = ("center", "shape")
_ESTIMATOR_KEYS = ("method", "law", "eps", "chain_poles", "b_poles", "Gamma", "theta_hat0",
                   "x_hat0", "theta_star", "excitation", "on_invalid", "A_design", "E_design",
                   "second", "allow_nonminimum_phase", "x_hat0_from_y")
#: The values of ``[estimator] method``: the paper's estimator, the two-stage guarded one, the
#: offline MAP fits.
ESTIMATION_METHODS = ("paper", "guarded", "mle", "ekf")
_SECOND_KEYS = ("eps2", "chain_poles", "b_poles", "g_on_estimates")
_SCENARIO_KEYS = ("theta", "x0", "t_end", "fs", "noise_std", "u_amplitudes", "u_frequencies",
                  "method", "rtol", "atol")
#: Integrators a ``[scenario]`` may name (``scipy.integrate.solve_ivp`` methods).
SCENARIO_METHODS = ("Radau", "BDF", "LSODA", "RK45", "RK23", "DOP853")


# ---------------------------------------------------------------------------------------------
# Reading and checking values
# ---------------------------------------------------------------------------------------------

def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class _Section:
    """One table of the file, with messages that name the file, the table and the key."""

    def __init__(self, source: str, name: str, table: Any) -> None:
        if not isinstance(table, Mapping):
            raise ModelFileError(f"model file {source}: [{name}] must be a table; got "
                                 f"{_show(table)}.")
        self.source, self.name, self.table = source, name, table

    def fail(self, key: str | None, message: str) -> ModelFileError:
        where = f"[{self.name}]" + (f" {key}" if key else "")
        return ModelFileError(f"model file {self.source}: {where}: {message}")

    def check_keys(self, allowed: Sequence[str]) -> None:
        unknown = [k for k in self.table if k not in allowed]
        if unknown:
            raise self.fail(None, f"unknown key(s) {unknown}; expected only "
                                  f"{list(allowed)}.")

    def has(self, key: str) -> bool:
        return key in self.table

    def require(self, key: str, what: str) -> Any:
        if key not in self.table:
            raise self.fail(key, f"missing; expected {what}.")
        return self.table[key]

    def number(self, key: str, default: float | None = None, *, positive: bool = False) -> float:
        if key not in self.table and default is not None:
            return default
        v = self.require(key, "a number")
        if not _is_number(v) or not math.isfinite(v) or (positive and v <= 0):
            raise self.fail(key, f"expected a finite {'positive ' if positive else ''}number; "
                                 f"got {_show(v)}.")
        return float(v)

    def vector(self, key: str, size: int, what: str) -> FloatArray:
        v = self.require(key, f"{size} number(s) ({what})")
        if _is_number(v):
            v = [v]
        if not isinstance(v, list) or not all(_is_number(e) for e in v):
            raise self.fail(key, f"expected a list of {size} number(s) ({what}); got "
                                 f"{_show(v)}.")
        if len(v) != size:
            raise self.fail(key, f"expected {size} number(s) ({what}); got {len(v)}.")
        arr = np.array(v, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise self.fail(key, f"entries must be finite; got {v}.")
        return arr

    def names(self, key: str, what: str, *, allow_empty: bool) -> tuple[str, ...]:
        v = self.require(key, f"a list of names ({what})")
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list) or not all(isinstance(e, str) for e in v):
            raise self.fail(key, f"expected a list of names ({what}); got {_show(v)}.")
        if not v and not allow_empty:
            raise self.fail(key, f"expected at least one name ({what}); got [].")
        return tuple(v)

    def matrix(self, key: str, rows: int, cols: int | None, what: str) -> FloatArray:
        v = self.require(key, f"a {what} matrix as a nested list of rows of numbers")
        if v == [] and rows > 0 and cols == 0:
            return np.zeros((rows, 0))
        if not isinstance(v, list) or not v or not all(isinstance(row, list) for row in v):
            raise self.fail(key, f"expected a {what} matrix as a nested list of rows, e.g. "
                                 f"[[1.0, 0.0], [0.0, 1.0]]; got {_show(v)}.")
        lengths = [len(row) for row in v]
        if len(set(lengths)) != 1:
            raise self.fail(key, f"rows have different lengths {lengths}; a matrix needs "
                                 f"equal rows.")
        for i, row in enumerate(v):
            for j, e in enumerate(row):
                if not _is_number(e) or not math.isfinite(e):
                    raise self.fail(key, f"entry [{i}][{j}] = {_show(e)} is not a finite "
                                         f"number.")
        arr = np.array(v, dtype=np.float64)
        want = (rows, lengths[0] if cols is None else cols)
        if arr.shape != want:
            raise self.fail(key, f"expected shape {want} ({what}); got {arr.shape}.")
        return arr

    def poles(self, key: str, *, nested: bool) -> Any:
        if key not in self.table:
            return None
        v = self.table[key]
        lists = v if nested else [v]
        ok = isinstance(v, list) and all(isinstance(p, list) and p and
                                         all(_is_number(e) and math.isfinite(e) for e in p)
                                         for p in lists)
        if not ok:
            example = "[[-1.0, -2.0, -3.0]] (one list per chain)" if nested else "[-1.0, -2.0]"
            raise self.fail(key, f"expected real poles as {example}; got {_show(v)}.")
        return tuple(tuple(float(e) for e in p) for p in v) if nested else \
            tuple(float(e) for e in v)


def _check_nesting(text: str, source: str) -> None:
    """Refuse brackets nested deeper than MAX_FILE_NESTING before a recursive parser sees them.

    Brackets inside strings and after ``#`` comments are skipped, so valid files are never
    refused by this scan.
    """
    depth = deepest = 0
    quote = ""
    comment = False
    escaped = False
    for ch in text:
        if comment:
            comment = ch != "\n"
        elif quote:
            if escaped:
                escaped = False
            elif ch == "\\" and quote == '"':
                escaped = True
            elif ch == quote or (ch == "\n" and quote == "'"):
                quote = ""
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            comment = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
            if deepest > limits.MAX_FILE_NESTING:
                raise InputLimitError(
                    f"model file {source}: tables or lists are nested deeper than "
                    f"{limits.MAX_FILE_NESTING} levels (thetahat.limits.MAX_FILE_NESTING); a "
                    f"model file needs at most 3 (a table holding a matrix).")
        elif ch in "]}":
            depth = max(0, depth - 1)


def _parse_text(text: str, syntax: str, source: str) -> dict[str, Any]:
    if syntax not in ("toml", "json"):
        raise ModelFileError(f"model file {source}: unknown syntax {syntax!r}; use a .toml or "
                             f".json file (syntax 'toml' or 'json').")
    if not isinstance(text, str):
        raise ModelFileError(f"model file {source}: expected the file's text as a string; got "
                             f"{type(text).__name__}.")
    text = text.removeprefix("\ufeff")                   # a byte-order mark (Windows editors)
    _check_nesting(text, source)
    try:
        doc = tomllib.loads(text) if syntax == "toml" else \
            json.loads(text, object_pairs_hook=functools.partial(_json_object, source))
    except RecursionError as exc:
        raise InputLimitError(f"model file {source}: nested too deeply to parse.") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(f"model file {source} is not valid TOML: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"model file {source} is not valid JSON: {exc.msg} at line "
                             f"{exc.lineno}, column {exc.colno}.") from exc
    if not isinstance(doc, dict):
        raise ModelFileError(f"model file {source}: the top level must be a table (object).")
    _check_integers(doc, source, "")
    return doc


def _json_object(source: str, pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object; a key given twice is refused (as TOML does) instead of the last winning."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ModelFileError(f"model file {source}: the key {key!r} is given twice in one "
                                 f"object; keep one.")
        out[key] = value
    return out


def _check_integers(value: Any, source: str, where: str) -> None:
    """Refuse integers that do not fit a float64 (a 400-digit number), naming the key."""
    stack = [(value, where)]
    while stack:
        item, at = stack.pop()
        if isinstance(item, dict):
            stack.extend((v, f"{at}.{k}" if at else str(k)) for k, v in item.items())
        elif isinstance(item, list):
            stack.extend((v, f"{at}[{i}]") for i, v in enumerate(item))
        elif isinstance(item, int) and not isinstance(item, bool) and abs(item) > _FLOAT_MAX:
            raise ModelFileError(f"model file {source}: {at}: the integer with "
                                 f"{len(str(abs(item)))} digits is too large for a float64 "
                                 f"number (at most about 1.8e308).")


_FLOAT_MAX = int(sys.float_info.max)


# ---------------------------------------------------------------------------------------------
# The specification
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class SecondObserverOptions:
    """Settings of the second observer of Sec. VI (``[estimator.second]``).

    Attributes
    ----------
    eps2 : float
        ε of its high-gain design.
    chain_poles : tuple of tuple of float, or None
        Poles of each H_j (default −1, −2, …).
    b_poles : tuple of float, or None
        Poles of A_b − K_bb C_b.
    g_on_estimates : bool
        Evaluate g on C x̂₂ instead of the measured y (Sec. VIII).
    """

    eps2: float
    chain_poles: tuple[tuple[float, ...], ...] | None
    b_poles: tuple[float, ...] | None
    g_on_estimates: bool


@dataclass(frozen=True, slots=True, repr=False)
class EstimatorOptions:
    """The ``[estimator]`` table: gain design, update law (built) and initial values.

    Attributes
    ----------
    law : {"gradient", "least_squares", "algebraic", "intermittent"}
    method : {"paper", "guarded", "mle", "ekf"}
        How :func:`~thetahat.modelfile.run_estimator` estimates (default "paper").
    update_law : UpdateLaw
        The law, built and validated.
    eps : float
        ε > 0 of the modified high-gain design (the design warns when ε > 1).
    chain_poles, b_poles : tuple or None
        Poles of the design (None: the defaults of :func:`~thetahat.design.gains.high_gain`).
    theta_hat0 : ndarray, shape (p,)
        Initial parameter estimate, in Θ.
    x_hat0 : ndarray, shape (n,)
        Initial state estimate.
    A_design, E_design : ndarray or None
        The design system (Sec. VII–VIII), None when the gains are designed on A and E.
    second : SecondObserverOptions or None
    allow_nonminimum_phase : bool
        Design even when Assumption 1 fails (the explicit opt-out; default False).
    x_hat0_from_y : bool
        Start x̂ at x̂₀ + C⁺(y(0) − C x̂₀) on a record (default True), else at x̂₀.
    gamma_auto : bool
        ``Gamma = "auto"`` (the gradient and least-squares laws' default): Γ is chosen on the
        record by :func:`~thetahat.estimation.observer.auto_gain.information_gain` when the
        estimator runs;
        ``update_law`` holds Γ = I until then.
    """

    law: str
    update_law: UpdateLaw
    eps: float
    chain_poles: tuple[tuple[float, ...], ...] | None
    b_poles: tuple[float, ...] | None
    theta_hat0: FloatArray
    x_hat0: FloatArray
    A_design: FloatArray | None
    E_design: FloatArray | None
    second: SecondObserverOptions | None
    allow_nonminimum_phase: bool = False
    method: str = "paper"
    gamma_auto: bool = False
    x_hat0_from_y: bool = True

    def __repr__(self) -> str:
        method = "" if self.method == "paper" else f"method={self.method!r}, "
        return (f"EstimatorOptions(law={self.law!r}, {method}eps={self.eps:g}, "
                f"theta_hat0={self.theta_hat0.tolist()}, "
                f"design_system={self.A_design is not None or self.E_design is not None}, "
                f"second={self.second is not None})")


@dataclass(frozen=True, slots=True, repr=False)
class ScenarioOptions:
    """The ``[scenario]`` table: the simulated experiment of ``thetahat sweep``/``tune``.

    Attributes
    ----------
    theta : ndarray, shape (p,)
        The true parameter.
    x0 : ndarray, shape (n,)
        Initial state of the plant.
    t_end, fs : float
        Duration (s) and sampling frequency (Hz).
    noise_std : float
        Standard deviation of the white noise on y (0: none).
    u_amplitudes, u_frequencies : ndarray, shape (m, q)
        The input u_i(t) = Σ_j a_ij sin(2π f_ij t).
    method : str
        ``solve_ivp`` method.
    rtol : float
    atol : ndarray, shape (n,)
        Integrator tolerances.
    defaults : tuple of str
        The keys the file did not give (their defaults were used).
    """

    theta: FloatArray
    x0: FloatArray
    t_end: float
    fs: float
    noise_std: float
    u_amplitudes: FloatArray
    u_frequencies: FloatArray
    method: str
    rtol: float
    atol: FloatArray
    defaults: tuple[str, ...]

    def __repr__(self) -> str:
        return (f"ScenarioOptions(theta={self.theta.tolist()}, t_end={self.t_end:g}, "
                f"fs={self.fs:g}, noise_std={self.noise_std:g}, method={self.method!r}, "
                f"defaults={list(self.defaults)})")


@dataclass(frozen=True, slots=True, repr=False)
class ModelSpec:
    """A model file, read and validated: the system, its names and the estimator options.

    Attributes
    ----------
    source : str
        The file it was read from.
    name : str
    system : PerturbedLinearSystem
        With perturbation g and Θ.
    input_names, output_names, state_names, parameter_names : tuple of str
        The symbol names of u, y, x and θ.
    estimator : EstimatorOptions
        The ``[estimator]`` table.
    scenario : ScenarioOptions
        The simulated experiment (``[scenario]``, defaults where the file has none).
    data : DataMapping or None
        The ``[data]`` table: which variables of a data file are t, u and y, with scale and
        offset (None: the default column names).
    """

    source: str
    name: str
    system: PerturbedLinearSystem
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    state_names: tuple[str, ...]
    parameter_names: tuple[str, ...]
    estimator: EstimatorOptions
    scenario: ScenarioOptions
    data: DataMapping | None = None

    @property
    def layout(self) -> RecordLayout:
        """What the data readers and writers need of this model (:mod:`thetahat.io`): the
        names, k, the ``[data]`` table and the slowest time constant of A."""
        eig = np.abs(np.linalg.eigvals(self.system.A))
        eig = eig[eig > 1e-12 * max(1.0, float(eig.max(initial=0.0)))]
        return RecordLayout(input_names=self.input_names, output_names=self.output_names,
                            state_names=self.state_names, parameter_names=self.parameter_names,
                            k=self.system.k, data=self.data,
                            time_scale=1.0 / float(eig.min()) if eig.size else None)

    def __repr__(self) -> str:
        s = self.system
        return (f"ModelSpec(name={self.name!r}, n={s.n}, m={s.m}, r={s.r}, k={s.k}, p={s.p}, "
                f"estimator={self.estimator!r})")


@dataclass(frozen=True, slots=True)
class _ThetaStarExpression:
    """θ*(v, x, φ) read from the file: a parsed expression in u, y, x and φ."""

    expr: SymbolicPerturbation

    def __call__(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike) -> FloatArray:
        """θ*; shape (..., p)."""
        return self.expr.g(np.asarray(v, dtype=np.float64), np.asarray(x_hat, dtype=np.float64),
                           np.asarray(phi_hat, dtype=np.float64))

    @property
    def sympy_form(self) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
        """(θ* entries, their arguments col(u, y), x, φ in call order), for code printers."""
        e = self.expr
        return tuple(e.expr), (*e.u, *e.y, *e.x, *e.theta)


def _phi_names(k: int) -> list[str]:
    return ["phi"] if k == 1 else [f"phi{i + 1}" for i in range(k)]


def _read_perturbation(sec: _Section) -> tuple[SymbolicPerturbation, dict[str, Any]]:
    sec.check_keys(_PERTURBATION_KEYS)
    g = sec.require("g", "a formula string, or a list of strings (one per component of φ)")
    names = {"u": sec.names("u", "input names", allow_empty=True),
             "y": sec.names("y", "output names", allow_empty=False),
             "x": sec.names("x", "state names", allow_empty=False),
             "theta": sec.names("theta", "parameter names", allow_empty=False)}
    constants = sec.table.get("constants", {})
    if not isinstance(constants, Mapping):
        raise sec.fail("constants", f"expected a table of named numbers; got "
                                    f"{_show(constants)}.")
    try:
        pert = parse_perturbation(g, constants=constants, **names)
    except (ModelFileError, InputLimitError) as exc:
        raise sec.fail("g", str(exc)) from exc
    return pert, {"names": names, "constants": dict(constants)}


def _read_gamma(sec: _Section, p: int, law: str) -> tuple[FloatArray, bool]:
    """(Γ, auto): ``"auto"`` (the default of the gradient law) is resolved on the record by
    :func:`~thetahat.estimation.observer.auto_gain.information_gain`; Γ = 1 stands in until then."""
    G = sec.table.get("Gamma", "auto" if law in AUTO_GAMMA_LAWS else 1.0)
    if G == "auto":
        if law not in AUTO_GAMMA_LAWS:
            raise sec.fail("Gamma", f"'auto' is for the gradient and least-squares laws, whose "
                                    f"Γ must match the parameters' scales; the {law!r} law's Γ "
                                    "is a rate (1/s): give a positive number.")
        return np.eye(p), True
    rows = G if isinstance(G, list) else None
    numeric = _is_number(G) or (rows is not None and all(
        isinstance(r, list) and all(_is_number(e) for e in r) for r in rows))
    if not numeric:
        raise sec.fail("Gamma", f"expected a positive number, a {p} × {p} symmetric "
                                f"positive-definite matrix or 'auto'; got {_show(G)}.")
    try:
        return as_gain("Gamma", G, p), False
    except (ThetahatError, ValueError) as exc:
        raise sec.fail("Gamma", str(exc)) from exc


def _read_theta_star(sec: _Section, pert: SymbolicPerturbation,
                     parsed: dict[str, Any]) -> _ThetaStarExpression:
    p, k = pert.dims[3], pert.dims[4]
    names = parsed["names"]
    try:
        expr = parse_perturbation(sec.table["theta_star"], u=names["u"], y=names["y"],
                                  x=names["x"], theta=_phi_names(k),
                                  constants=parsed["constants"])
    except (ModelFileError, InputLimitError) as exc:
        raise sec.fail("theta_star", f"{exc} (θ* may use the names of u, y, x and "
                                     f"{', '.join(_phi_names(k))}).") from exc
    if expr.dims[4] != p:
        raise sec.fail("theta_star", f"expected {p} component(s), one per parameter; got "
                                     f"{expr.dims[4]}.")
    return _ThetaStarExpression(expr)


def _read_parameter_set(sec: _Section, p: int) -> ParameterSet:
    """Θ from [parameter_set]: a box (lower, upper), ball (center, radius) or ellipsoid
    (center, shape), told apart by their keys."""
    what = f"one per parameter in [perturbation] theta, p = {p}"
    try:
        if sec.has("radius"):
            sec.check_keys(_BALL_KEYS)
            return Ball(sec.vector("center", p, what), sec.number("radius", positive=True))
        if sec.has("shape"):
            sec.check_keys(_ELLIPSOID_KEYS)
            return Ellipsoid(sec.vector("center", p, what),
                             sec.matrix("shape", p, p, f"p × p, p = {p}"))
        if sec.has("center"):
            raise sec.fail("center", "a ball needs radius = R, an ellipsoid shape = Q (p × p); "
                                     "a box is given by lower and upper instead.")
        sec.check_keys(_BOX_KEYS)
        return Box(sec.vector("lower", p, what), sec.vector("upper", p, what))
    except ModelFileError:
        raise
    except ThetahatError as exc:
        raise sec.fail(None, str(exc)) from exc


def _read_law(sec: _Section, pert: SymbolicPerturbation, theta_set: ParameterSet,
              parsed: dict[str, Any]) -> tuple[str, UpdateLaw, bool]:
    law = sec.require("law", f"one of {list(LAWS)}")
    if law not in LAWS:
        raise sec.fail("law", f"unknown law {_show(law)}; expected one of {list(LAWS)} "
                              f"(Sec. IV).")
    for key in ("theta_star", "excitation", "on_invalid"):
        unused = law in AUTO_GAMMA_LAWS or (key == "excitation" and law != "intermittent")
        if sec.has(key) and unused:
            raise sec.fail(key, f"not used by the {law!r} law; remove it.")
    Gamma, auto = _read_gamma(sec, theta_set.dim, law)
    if law == "gradient":
        try:
            return law, GradientInversion(pert, Gamma, theta_set), auto
        except ThetahatError as exc:
            raise sec.fail("law", str(exc)) from exc
    if law == "least_squares":
        try:
            return law, FilteredLeastSquares(pert, Gamma, theta_set), auto
        except ThetahatError as exc:
            raise sec.fail("law", str(exc)) from exc
    on_invalid = sec.table.get("on_invalid", "raise")
    if on_invalid not in ("raise", "freeze"):
        raise sec.fail("on_invalid", f"expected 'raise' or 'freeze'; got {_show(on_invalid)}.")
    theta_star = _read_theta_star(sec, pert, parsed) if sec.has("theta_star") else None
    ramp = None
    if law == "intermittent":
        lo_hi = sec.require("excitation", "[low, high], the thresholds on ‖φ̂‖ of the smooth "
                                          "excitation weight of the intermittent law")
        if not (isinstance(lo_hi, list) and len(lo_hi) == 2
                and all(_is_number(e) for e in lo_hi)):
            raise sec.fail("excitation", f"expected [low, high]; got {_show(lo_hi)}.")
        try:
            ramp = smooth_ramp(*lo_hi)
        except ThetahatError as exc:
            raise sec.fail("excitation", str(exc)) from exc
    try:
        if theta_star is None:
            opts = {"Gamma": Gamma, "parameter_set": theta_set, "on_invalid": on_invalid}
            built = (AlgebraicInversion.from_perturbation(  # type: ignore[attr-defined]
                pert, **opts) if law == "algebraic"
                else IntermittentInversion.from_perturbation(pert, ramp, **opts))
        elif law == "algebraic":
            built = AlgebraicInversion(theta_star, Gamma, theta_set, on_invalid=on_invalid)
        else:
            built = IntermittentInversion(theta_star, ramp, Gamma, theta_set,
                                          on_invalid=on_invalid)
    except ThetahatError as exc:
        if theta_star is None:
            raise sec.fail("theta_star", f"not given, and it cannot be derived from g: {exc}"
                           ) from exc
        raise sec.fail("law", str(exc)) from exc
    return law, built, False


def _read_estimator(sec: _Section, system: PerturbedLinearSystem, pert: SymbolicPerturbation,
                    parsed: dict[str, Any]) -> EstimatorOptions:
    sec.check_keys(_ESTIMATOR_KEYS)
    n, k, p = system.n, system.k, system.p
    law, update_law, gamma_auto = _read_law(sec, pert, system.require_parameter_set("[estimator]"), parsed)
    method = sec.table.get("method", "paper")
    if method not in ESTIMATION_METHODS:
        raise sec.fail("method", f"unknown method {_show(method)}; expected one of "
                                 f"{list(ESTIMATION_METHODS)}.")
    eps = sec.number("eps", 1.0, positive=True)
    theta_hat0 = (sec.vector("theta_hat0", p, f"θ̂(0), p = {p}") if sec.has("theta_hat0")
                  else None)
    try:
        theta_hat0 = update_law.init(theta_hat0)
    except ThetahatError as exc:
        raise sec.fail("theta_hat0", str(exc)) from exc
    x_hat0 = sec.vector("x_hat0", n, f"x̂(0), n = {n}") if sec.has("x_hat0") else np.zeros(n)
    A_d = sec.matrix("A_design", n, n, "n × n") if sec.has("A_design") else None
    E_d = sec.matrix("E_design", n, k, "n × k") if sec.has("E_design") else None
    second = None
    if sec.has("second"):
        s2 = _Section(sec.source, "estimator.second", sec.table["second"])
        s2.check_keys(_SECOND_KEYS)
        on_est = s2.table.get("g_on_estimates", False)
        if not isinstance(on_est, bool):
            raise s2.fail("g_on_estimates", f"expected true or false; got {_show(on_est)}.")
        eps2 = s2.number("eps2", 1.0, positive=True)
        second = SecondObserverOptions(eps2=eps2,
                                       chain_poles=s2.poles("chain_poles", nested=True),
                                       b_poles=s2.poles("b_poles", nested=False),
                                       g_on_estimates=on_est)
    allow_nmp = sec.table.get("allow_nonminimum_phase", False)
    if not isinstance(allow_nmp, bool):
        raise sec.fail("allow_nonminimum_phase", f"expected true or false; got "
                                                 f"{_show(allow_nmp)}.")
    from_y = sec.table.get("x_hat0_from_y", True)
    if not isinstance(from_y, bool):
        raise sec.fail("x_hat0_from_y", f"expected true or false; got {_show(from_y)}.")
    for arr in (theta_hat0, x_hat0, A_d, E_d):
        if arr is not None:
            arr.setflags(write=False)
    return EstimatorOptions(law=law, update_law=update_law, eps=eps,
                            chain_poles=sec.poles("chain_poles", nested=True),
                            b_poles=sec.poles("b_poles", nested=False),
                            theta_hat0=theta_hat0, x_hat0=x_hat0, A_design=A_d, E_design=E_d,
                            second=second, allow_nonminimum_phase=allow_nmp,
                            method=method, gamma_auto=gamma_auto, x_hat0_from_y=from_y)


def _scenario_input(sec: _Section, m: int) -> tuple[FloatArray, FloatArray]:
    """(amplitudes, frequencies), each (m, q): one list for every channel or one per channel."""
    out = []
    for key, default in (("u_amplitudes", [1.0, 0.5]), ("u_frequencies", [0.1, 0.3])):
        v = sec.table.get(key, default)
        rows = v if (isinstance(v, list) and v and isinstance(v[0], list)) else [v] * m
        ok = isinstance(v, list) and len(rows) == m and all(
            isinstance(r, list) and r and all(_is_number(e) and math.isfinite(e) for e in r)
            for r in rows)
        if not ok:
            raise sec.fail(key, f"expected a list of numbers (used for every input) or {m} "
                                f"lists (one per input); got {_show(v)}.")
        out.append(np.array(rows, dtype=np.float64).reshape(m, -1) if m else np.zeros((0, 1)))
    amp, freq = out
    if amp.shape != freq.shape:
        raise sec.fail("u_frequencies", f"expected the shape of u_amplitudes {amp.shape}; got "
                                        f"{freq.shape}.")
    if np.any(freq < 0):
        raise sec.fail("u_frequencies", "frequencies must be >= 0 Hz.")
    return amp, freq


def _read_scenario(sec: _Section, system: PerturbedLinearSystem, theta_set: ParameterSet
                   ) -> ScenarioOptions:
    sec.check_keys(_SCENARIO_KEYS)
    n, m, p = system.n, system.m, system.p
    if sec.has("theta"):
        theta = sec.vector("theta", p, f"the true θ, p = {p}")
        if not theta_set.contains(theta):
            raise sec.fail("theta", f"the true θ = {theta.tolist()} lies outside Θ = "
                                    f"{theta_set!r}; the estimator assumes θ ∈ Θ.")
    else:
        # half way from Θ's centre to its point nearest the bounding box's upper corner (for a
        # box: three quarters of the way from lower to upper)
        centre = np.asarray(theta_set.interior_point, dtype=np.float64)
        corner = theta_set.nearest(theta_bounds(theta_set)[1])
        theta = centre + 0.5 * (corner - centre)
    x0 = sec.vector("x0", n, f"x(0), n = {n}") if sec.has("x0") else np.zeros(n)
    method = sec.table.get("method", "Radau")
    if method not in SCENARIO_METHODS:
        raise sec.fail("method", f"expected one of {list(SCENARIO_METHODS)}; got "
                                 f"{_show(method)}.")
    noise = sec.number("noise_std", 0.01) if sec.has("noise_std") else 0.01
    if noise < 0:
        raise sec.fail("noise_std", f"expected a number >= 0; got {noise}.")
    atol_v = sec.table.get("atol", 1e-10)
    atol = (np.full(n, float(atol_v)) if _is_number(atol_v) and atol_v > 0
            else sec.vector("atol", n, f"tolerances > 0, n = {n}"))
    if np.any(atol <= 0):
        raise sec.fail("atol", f"tolerances must be > 0; got {atol.tolist()}.")
    amp, freq = _scenario_input(sec, m)
    for arr in (theta, x0, atol, amp, freq):
        arr.setflags(write=False)
    return ScenarioOptions(theta=theta, x0=x0, t_end=sec.number("t_end", 20.0, positive=True),
                           fs=sec.number("fs", 100.0, positive=True), noise_std=noise,
                           u_amplitudes=amp, u_frequencies=freq, method=method,
                           rtol=sec.number("rtol", 1e-8, positive=True), atol=atol,
                           defaults=tuple(k for k in _SCENARIO_KEYS if not sec.has(k)))


#: A minimal model file (the Proposition 3 example of ``examples/prop3.toml`` without its
#: comments), used by the examples in the docstrings.
EXAMPLE_MODEL = """
name = "Oscillator with a monotone perturbation (Proposition 3)"
[system]
A = [[0.0, 1.0], [-1.0, -0.5]]
B = [[0.0], [1.0]]
C = [[1.0, 0.0]]
E = [[0.0], [1.0]]
[perturbation]
g = "(2 + sin(y))*(theta + theta**3/3)"
u = ["u"]
y = ["y"]
x = ["x1", "x2"]
theta = ["theta"]
[parameter_set]
lower = [-2.0]
upper = [2.0]
[estimator]
law = "gradient"
Gamma = 2.0
theta_hat0 = [0.0]
eps = 0.5
[estimator.second]
eps2 = 1.0
"""


def load_model(path: str | Path) -> ModelSpec:
    """Read a model file (TOML or JSON, by suffix; see the module docstring).

    Parameters
    ----------
    path : str or Path
        A ``.toml`` or ``.json`` file.

    Returns
    -------
    ModelSpec

    Raises
    ------
    ModelFileError
        The file cannot be read or parsed, a table or key is missing or unknown, a matrix
        has the wrong shape, a formula is not allowed (e.g. ``__import__``), the law is
        unknown, θ̂(0) lies outside Θ, ...; the message names the section and key.

    Notes
    -----
    The gains are designed by :func:`build_observer` and :func:`analyze_model` (a design
    failure, e.g. a wrong number of chain poles, is reported there).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL, load_model
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "prop3.toml"
    >>> _ = path.write_text(EXAMPLE_MODEL)
    >>> spec = load_model(path)
    >>> spec.system.n, spec.system.p, spec.estimator.law, spec.state_names
    (2, 1, 'gradient', ('x1', 'x2'))
    """
    path = Path(path)
    syntax = path.suffix.lower().lstrip(".")
    if syntax not in ("toml", "json"):
        raise ModelFileError(f"model file {path}: unknown type {path.suffix or '(no suffix)'!r}"
                             f"; use a .toml or .json file.")
    text = read_text(path, "model file", limits.MAX_MODEL_FILE_BYTES)   # regular files only
    return loads_model(text, syntax=syntax, source=str(path))


def loads_model(text: str, *, syntax: str = "toml", source: str = "<string>") -> ModelSpec:
    """Read a model from text in model-file syntax (see the module docstring).

    Parameters
    ----------
    text : str
        The content of a model file.
    syntax : {"toml", "json"}
    source : str
        Name used in messages and stored in ``ModelSpec.source``.

    Returns
    -------
    ModelSpec

    Raises
    ------
    ModelFileError
        As for :func:`load_model`.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> spec.estimator
    EstimatorOptions(law='gradient', eps=0.5, theta_hat0=[0.0], design_system=False, second=True)
    >>> loads_model(EXAMPLE_MODEL.replace('"gradient"', '"newton"'))
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: model file <string>: [estimator] law: unknown law 'newton'; expected one of ['gradient', 'least_squares', 'algebraic', 'intermittent'] (Sec. IV).
    """
    doc = _parse_text(text, syntax, source)
    top = _Section(source, "top level", doc)
    top.check_keys(_TOP_KEYS)
    name = doc.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise top.fail("name", f"expected a string; got {_show(name)}.")
    sections = {}
    for key in ("system", "perturbation", "parameter_set", "estimator"):
        if key not in doc:
            raise ModelFileError(f"model file {source}: missing table [{key}].")
        sections[key] = _Section(source, key, doc[key])
    pert, parsed = _read_perturbation(sections["perturbation"])
    n, m, r, p, k = pert.dims
    sys_sec = sections["system"]
    sys_sec.check_keys(_SYSTEM_KEYS)
    A = sys_sec.matrix("A", n, n, f"n × n with n = {n} states from [perturbation] x")
    B = sys_sec.matrix("B", n, m, f"n × m with m = {m} inputs from [perturbation] u")
    C = sys_sec.matrix("C", r, n, f"r × n with r = {r} outputs from [perturbation] y")
    E = sys_sec.matrix("E", n, k, f"n × k with k = {k} components of [perturbation] g")
    theta_set = _read_parameter_set(sections["parameter_set"], p)
    try:
        system = PerturbedLinearSystem(A=A, B=B, C=C, E=E, perturbation=pert,
                                       parameter_set=theta_set)
    except ThetahatError as exc:
        raise ModelFileError(f"model file {source}: [system]: {exc}") from exc
    estimator = _read_estimator(sections["estimator"], system, pert, parsed)
    scenario = _read_scenario(_Section(source, "scenario", doc.get("scenario", {})), system,
                              theta_set)
    names = parsed["names"]
    data = None
    if "data" in doc:
        data_sec = _Section(source, "data", doc["data"])
        data = parse_data_table(data_sec.table, names["u"], names["y"],
                                lambda message: data_sec.fail(None, message))
    return ModelSpec(source=source, name=name, system=system, input_names=names["u"],
                     output_names=names["y"], state_names=names["x"],
                     parameter_names=names["theta"], estimator=estimator, scenario=scenario,
                     data=data)
