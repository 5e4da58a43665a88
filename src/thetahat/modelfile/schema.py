"""Model-file schema: reading and validating a model file into a :class:`ModelSpec`.

A model file (TOML, read with :mod:`tomllib`, or JSON with the same structure) has the
sections ``[system]`` (A, B, C, E of (1)), ``[perturbation]`` (g and the names),
``[parameter_set]`` (Θ: a box, a ball or an ellipsoid), the optional ``[state_set]`` (X, the
box the states stay in, outside which g is saturated: Remark 1), ``[estimator]`` (the gain design, the
update law (8), the initial values, the method) with an optional ``[estimator.second]`` (the
second observer of Sec. VI), and the optional ``[scenario]`` (the simulated experiment of
``thetahat sweep`` and ``thetahat tune``) and ``[data]`` (which columns of a log are t, u and
y, in what units: :mod:`thetahat.io.mapping`).

Every key, with its type, default, an example and its meaning, is a row of the tables of
:mod:`~thetahat.modelfile.keys`, which the loader validates against: unknown keys are errors
(they are usually typos), and every problem is reported as a
:class:`~thetahat.errors.ModelFileError` naming the file, the section and the key. The
reference of the format, the page reference/model-file.md of the documentation, is generated
from those tables.

Data files for :func:`thetahat.io.datafile.read_data` are CSV with a header row, Parquet,
MATLAB (``.mat``, v4–v7) or Excel files. Without ``[data]``, they hold a column ``t``
(strictly increasing), one column per input, named as in ``[perturbation] u`` or ``u1``,
``u2``, … (``u`` also works when m = 1), and one per output, named as in ``[perturbation] y``
or ``y1``, … (``y`` when r = 1). Column order is free and other columns are ignored.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import limits
from ..io.mapping import DataMapping, RecordLayout, parse_data_table
from ..errors import InputLimitError, ModelFileError, ThetahatError
from ..estimation.observer.laws import (
    AlgebraicInversion,
    algebraic_from_perturbation,
    GradientInversion,
    IntermittentInversion,
    UpdateLaw,
    smooth_ramp,
)
from ..estimation.observer.laws.least_squares import FilteredLeastSquares
from ..estimation.observer.laws.projection import as_gain
from ..estimation.protocol import SignalNames
from ..estimation.statistical.stage2_set import theta_bounds
from ..model.paramset import Ball, Box, Ellipsoid, ParameterSet
from ..model.parse import parse_perturbation
from ..model.perturbation import SymbolicPerturbation
from ..model.state_set import StateSet, StateSetError, saturate_states
from ..methods import DEFAULT_METHOD
from ..model.system import PerturbedLinearSystem
from ..safe_io import read_text
from . import keys as K
from .keys import AUTO_GAMMA_LAWS
from .section import Section, is_number, show
from .text import parse_model_text

__all__ = ["EXAMPLE_MODEL", "EstimatorOptions", "ModelSpec", "ScenarioOptions",
           "SecondObserverOptions", "load_model", "loads_model"]

FloatArray = NDArray[np.float64]


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
    method : str
        How :func:`~thetahat.modelfile.run_estimator` estimates: one of
        :data:`thetahat.methods.ESTIMATION_METHODS` (default
        :data:`thetahat.methods.DEFAULT_METHOD`, "guarded").
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
    method_given : bool
        The file names its ``method`` (``thetahat codegen`` refuses a file that names one
        without a C form; a file that names none gets the paper's observer there).
    gamma_auto : bool
        ``Gamma = "auto"`` (the gradient and least-squares laws' default): Γ is chosen on the
        record by :func:`~thetahat.estimation.observer.auto_gain.information_gain` when the
        estimator runs;
        ``update_law`` holds Γ = I until then.
    eps_auto : bool
        ``eps = "auto"``: ε is chosen on the record by
        :func:`~thetahat.modelfile.assembly.auto_eps` when the estimator runs; ``eps`` holds
        1 until then.
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
    method: str = DEFAULT_METHOD
    gamma_auto: bool = False
    eps_auto: bool = False
    x_hat0_from_y: bool = True
    method_given: bool = False

    def __repr__(self) -> str:
        method = "" if self.method == DEFAULT_METHOD else f"method={self.method!r}, "
        eps = "'auto'" if self.eps_auto else f"{self.eps:g}"
        return (f"EstimatorOptions(law={self.law!r}, {method}eps={eps}, "
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
    u_hold : {"continuous", "zoh"}
        The input the plant sees: the sines, or their samples at ``fs`` held by a DAC.
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
    u_hold: str
    method: str
    rtol: float
    atol: FloatArray
    defaults: tuple[str, ...]

    def __repr__(self) -> str:
        return (f"ScenarioOptions(theta={self.theta.tolist()}, t_end={self.t_end:g}, "
                f"fs={self.fs:g}, noise_std={self.noise_std:g}, u_hold={self.u_hold!r}, "
                f"method={self.method!r}, defaults={list(self.defaults)})")


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
    state_set : StateSet or None
        X of ``[state_set]``; when given, ``system``'s g is already saturated outside it
        (:func:`~thetahat.model.state_set.saturate_states`).
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
    state_set: StateSet | None = None

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

    @property
    def signal_names(self) -> SignalNames:
        """The names of the states, parameters, inputs and outputs (for results and tables)."""
        return SignalNames(states=self.state_names, parameters=self.parameter_names,
                           inputs=self.input_names, outputs=self.output_names)

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


def _read_perturbation(sec: Section) -> tuple[SymbolicPerturbation, dict[str, Any]]:
    sec.check_keys()
    g = sec.require("g", "a formula string, or a list of strings (one per component of φ)")
    names = {"u": sec.names("u", "input names", allow_empty=True),
             "y": sec.names("y", "output names", allow_empty=False),
             "x": sec.names("x", "state names", allow_empty=False),
             "theta": sec.names("theta", "parameter names", allow_empty=False)}
    constants = sec.get("constants")
    if not isinstance(constants, Mapping):
        raise sec.fail("constants", f"expected a table of named numbers; got "
                                    f"{show(constants)}.")
    try:
        pert = parse_perturbation(g, constants=constants, **names)
    except (ModelFileError, InputLimitError) as exc:
        raise sec.fail("g", str(exc)) from exc
    return pert, {"names": names, "constants": dict(constants)}


def _read_gamma(sec: Section, p: int, law: str) -> tuple[FloatArray, bool]:
    """(Γ, auto): ``"auto"`` (the default of the gradient law) is resolved on the record by
    :func:`~thetahat.estimation.observer.auto_gain.information_gain`; Γ = 1 stands in until then."""
    G = sec.get("Gamma")
    if G is None:                                          # the default depends on the law
        G = "auto" if law in AUTO_GAMMA_LAWS else 1.0
    if G == "auto":
        if law not in AUTO_GAMMA_LAWS:
            raise sec.fail("Gamma", f"'auto' is for the gradient and least-squares laws, whose "
                                    f"Γ must match the parameters' scales; the {law!r} law's Γ "
                                    "is a rate (1/s): give a positive number.")
        return np.eye(p), True
    rows = G if isinstance(G, list) else None
    numeric = is_number(G) or (rows is not None and all(
        isinstance(r, list) and all(is_number(e) for e in r) for r in rows))
    if not numeric:
        raise sec.fail("Gamma", f"expected a positive number, a {p} × {p} symmetric "
                                f"positive-definite matrix or 'auto'; got {show(G)}.")
    try:
        return as_gain("Gamma", G, p), False
    except (ThetahatError, ValueError) as exc:
        raise sec.fail("Gamma", str(exc)) from exc


def _read_theta_star(sec: Section, pert: SymbolicPerturbation,
                     parsed: dict[str, Any]) -> _ThetaStarExpression:
    p, k = pert.dims[3], pert.dims[4]
    names = parsed["names"]
    try:
        expr = parse_perturbation(sec.get("theta_star"), u=names["u"], y=names["y"],
                                  x=names["x"], theta=_phi_names(k),
                                  constants=parsed["constants"])
    except (ModelFileError, InputLimitError) as exc:
        raise sec.fail("theta_star", f"{exc} (θ* may use the names of u, y, x and "
                                     f"{', '.join(_phi_names(k))}).") from exc
    if expr.dims[4] != p:
        raise sec.fail("theta_star", f"expected {p} component(s), one per parameter; got "
                                     f"{expr.dims[4]}.")
    return _ThetaStarExpression(expr)


def _read_parameter_set(sec: Section, p: int) -> ParameterSet:
    """Θ from [parameter_set]: a box (lower, upper), ball (center, radius) or ellipsoid
    (center, shape), told apart by their keys."""
    what = f"one per parameter in [perturbation] theta, p = {p}"
    try:
        if sec.has("radius"):
            sec = sec.as_form(K.PARAMETER_SET_BALL)
            sec.check_keys()
            return Ball(sec.vector("center", p, what), sec.number("radius"))
        if sec.has("shape"):
            sec = sec.as_form(K.PARAMETER_SET_ELLIPSOID)
            sec.check_keys()
            return Ellipsoid(sec.vector("center", p, what),
                             sec.matrix("shape", p, p, f"p × p, p = {p}"))
        if sec.has("center"):
            raise sec.fail("center", "a ball needs radius = R, an ellipsoid shape = Q (p × p); "
                                     "a box is given by lower and upper instead.")
        sec.check_keys()
        return Box(sec.vector("lower", p, what), sec.vector("upper", p, what))
    except ModelFileError:
        raise
    except ThetahatError as exc:
        raise sec.fail(None, str(exc)) from exc


def _read_state_set(sec: Section, n: int) -> StateSet:
    """X from [state_set]: a box with finite faces (Remark 1)."""
    what = f"one per state in [perturbation] x, n = {n}"
    sec.check_keys()
    try:
        return StateSet(sec.vector("lower", n, what), sec.vector("upper", n, what))
    except StateSetError as exc:
        raise sec.fail(None, str(exc)) from exc


def _read_system(sec: Section, pert: SymbolicPerturbation, set_sec: Section
                 ) -> PerturbedLinearSystem:
    """The system (1) from [system] (its sizes from [perturbation]) and [parameter_set]."""
    n, m, r, p, k = pert.dims
    sec.check_keys()
    A = sec.matrix("A", n, n, f"n × n with n = {n} states from [perturbation] x")
    B = sec.matrix("B", n, m, f"n × m with m = {m} inputs from [perturbation] u")
    C = sec.matrix("C", r, n, f"r × n with r = {r} outputs from [perturbation] y")
    E = sec.matrix("E", n, k, f"n × k with k = {k} components of [perturbation] g")
    theta_set = _read_parameter_set(set_sec, p)
    try:
        return PerturbedLinearSystem(A=A, B=B, C=C, E=E, perturbation=pert,
                                     parameter_set=theta_set)
    except ThetahatError as exc:
        raise ModelFileError(f"model file {sec.source}: [system]: {exc}") from exc


def _read_law(sec: Section, pert: SymbolicPerturbation, theta_set: ParameterSet,
              parsed: dict[str, Any]) -> tuple[str, UpdateLaw, bool]:
    law = sec.choice("law")
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
    on_invalid = cast(Literal["raise", "freeze"], sec.choice("on_invalid"))
    theta_star = _read_theta_star(sec, pert, parsed) if sec.has("theta_star") else None
    ramp = None
    if law == "intermittent":
        lo_hi = sec.require("excitation", "[low, high], the thresholds on ‖φ̂‖ of the smooth "
                                          "excitation weight of the intermittent law")
        if not (isinstance(lo_hi, list) and len(lo_hi) == 2
                and all(is_number(e) for e in lo_hi)):
            raise sec.fail("excitation", f"expected [low, high]; got {show(lo_hi)}.")
        try:
            ramp = smooth_ramp(*lo_hi)
        except ThetahatError as exc:
            raise sec.fail("excitation", str(exc)) from exc
    try:
        if theta_star is None:
            opts: dict[str, Any] = {"Gamma": Gamma, "parameter_set": theta_set,
                                    "on_invalid": on_invalid}
            built = (algebraic_from_perturbation(pert, **opts) if law == "algebraic"
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


def _read_second(sec: Section) -> SecondObserverOptions:
    s2 = Section(sec.source, K.SECOND, sec.get("second"))
    s2.check_keys()
    on_est = s2.boolean("g_on_estimates")
    return SecondObserverOptions(eps2=s2.number("eps2"), chain_poles=s2.poles("chain_poles"),
                                 b_poles=s2.poles("b_poles"), g_on_estimates=on_est)


def _read_estimator(sec: Section, system: PerturbedLinearSystem, pert: SymbolicPerturbation,
                    parsed: dict[str, Any]) -> EstimatorOptions:
    sec.check_keys()
    n, k, p = system.n, system.k, system.p
    law, update_law, gamma_auto = _read_law(sec, pert, system.require_parameter_set(
        "[estimator]"), parsed)
    method = sec.choice("method")
    eps_auto = sec.get("eps") == "auto"
    eps = 1.0 if eps_auto else sec.number("eps")
    theta_hat0 = (sec.vector("theta_hat0", p, f"θ̂(0), p = {p}") if sec.has("theta_hat0")
                  else None)
    try:
        theta_hat0 = update_law.init(theta_hat0)
    except ThetahatError as exc:
        raise sec.fail("theta_hat0", str(exc)) from exc
    x_hat0 = sec.vector("x_hat0", n, f"x̂(0), n = {n}") if sec.has("x_hat0") else np.zeros(n)
    A_d = sec.matrix("A_design", n, n, "n × n") if sec.has("A_design") else None
    E_d = sec.matrix("E_design", n, k, "n × k") if sec.has("E_design") else None
    second = _read_second(sec) if sec.has("second") else None
    allow_nmp = sec.boolean("allow_nonminimum_phase")
    from_y = sec.boolean("x_hat0_from_y")
    for arr in (theta_hat0, x_hat0, A_d, E_d):
        if arr is not None:
            arr.setflags(write=False)
    return EstimatorOptions(law=law, update_law=update_law, eps=eps,
                            chain_poles=sec.poles("chain_poles"), b_poles=sec.poles("b_poles"),
                            theta_hat0=theta_hat0, x_hat0=x_hat0, A_design=A_d, E_design=E_d,
                            second=second, allow_nonminimum_phase=allow_nmp,
                            method=method, gamma_auto=gamma_auto, eps_auto=eps_auto,
                            x_hat0_from_y=from_y,
                            method_given=sec.has("method"))


def _scenario_input(sec: Section, m: int) -> tuple[FloatArray, FloatArray]:
    """(amplitudes, frequencies), each (m, q): one list for every channel or one per channel."""
    out = []
    for key in ("u_amplitudes", "u_frequencies"):
        v = sec.get(key)
        rows = v if (isinstance(v, list) and v and isinstance(v[0], list)) else [v] * m
        ok = isinstance(v, list) and len(rows) == m and all(
            isinstance(r, list) and r and all(is_number(e) and math.isfinite(e) for e in r)
            for r in rows)
        if not ok:
            raise sec.fail(key, f"expected a list of numbers (used for every input) or {m} "
                                f"lists (one per input); got {show(v)}.")
        out.append(np.array(rows, dtype=np.float64).reshape(m, -1) if m else np.zeros((0, 1)))
    amp, freq = out
    if amp.shape != freq.shape:
        raise sec.fail("u_frequencies", f"expected the shape of u_amplitudes {amp.shape}; got "
                                        f"{freq.shape}.")
    if np.any(freq < 0):
        raise sec.fail("u_frequencies", "frequencies must be >= 0 Hz.")
    return amp, freq


def _read_scenario(sec: Section, system: PerturbedLinearSystem, theta_set: ParameterSet
                   ) -> ScenarioOptions:
    sec.check_keys()
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
    method = sec.choice("method")
    noise = sec.number("noise_std")
    atol_v = sec.get("atol")
    atol = (np.full(n, float(atol_v)) if is_number(atol_v) and atol_v > 0
            else sec.vector("atol", n, f"tolerances > 0, n = {n}"))
    if np.any(atol <= 0):
        raise sec.fail("atol", f"tolerances must be > 0; got {atol.tolist()}.")
    amp, freq = _scenario_input(sec, m)
    for arr in (theta, x0, atol, amp, freq):
        arr.setflags(write=False)
    return ScenarioOptions(theta=theta, x0=x0, t_end=sec.number("t_end"), fs=sec.number("fs"),
                           noise_std=noise, u_amplitudes=amp, u_frequencies=freq,
                           u_hold=sec.choice("u_hold"), method=method,
                           rtol=sec.number("rtol"), atol=atol,
                           defaults=tuple(k for k in sec.keys.names() if not sec.has(k)))


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
    thetahat.errors.ModelFileError: model file <string>: [estimator] law: unknown law 'newton'; expected one of ['gradient', 'least_squares', 'algebraic', 'intermittent'].
    """
    doc = parse_model_text(text, syntax, source)
    top = Section(source, K.TOP, doc)
    top.check_keys()
    name = doc.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise top.fail("name", f"expected a string; got {show(name)}.")
    tables = {t.section: t for t in (K.SYSTEM, K.PERTURBATION, K.PARAMETER_SET_BOX,
                                     K.ESTIMATOR)}       # a box until its keys say otherwise
    sections = {}
    for row in K.TOP.keys:
        if row.required:
            if row.key not in doc:
                raise ModelFileError(f"model file {source}: missing table [{row.key}].")
            sections[row.key] = Section(source, tables[row.key], doc[row.key])
    pert, parsed = _read_perturbation(sections["perturbation"])
    state_set = None
    if "state_set" in doc:                       # g redefined outside X (Remark 1)
        state_set = _read_state_set(Section(source, K.STATE_SET, doc["state_set"]),
                                    pert.dims[0])
        pert = saturate_states(pert, state_set)
    system = _read_system(sections["system"], pert, sections["parameter_set"])
    estimator = _read_estimator(sections["estimator"], system, pert, parsed)
    scenario = _read_scenario(Section(source, K.SCENARIO, doc.get("scenario", {})), system,
                              system.require_parameter_set("[scenario]"))
    names = parsed["names"]
    data = None
    if "data" in doc:
        data_sec = Section(source, K.DATA, doc["data"])
        data_sec.check_keys()
        data = parse_data_table(data_sec.value, names["u"], names["y"],
                                lambda message: data_sec.fail(None, message))
    return ModelSpec(source=source, name=name, system=system, input_names=names["u"],
                     output_names=names["y"], state_names=names["x"],
                     parameter_names=names["theta"], estimator=estimator, scenario=scenario,
                     data=data, state_set=state_set)
