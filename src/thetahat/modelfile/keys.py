"""The keys of a model file, as data: one :class:`Table` per section.

Each table row is one key with its columns ``section``, ``key``, ``type``, ``default``,
``example`` and ``description`` (:data:`COLUMNS`, :meth:`Table.rows`). The loader
(:mod:`.schema`, through :class:`~thetahat.modelfile.section.Section`) validates every file
against these tables: a key that is not in its section's table is refused, a ``required`` key
must be given, a key that is absent takes the table's default, and the keys of type
``boolean``, ``choice`` and ``number`` are checked by their type alone. The readers of the
other types (matrices, names, poles, …) take their sizes from the rest of the file and their
requiredness and defaults from here. The inline tables of ``[data]`` (a signal,
:data:`DATA_SIGNAL`, and a time base, :data:`DATA_RATE`) are read by
:func:`thetahat.io.mapping.parse_data_table`, below the model files, whose keys and defaults
the tests hold to these rows. The reference of the model-file format
(docs/reference/model-file.md) is generated from :data:`TABLES` when the site is built
(docs/hooks/model_file.py).

A default is a value (the loader uses it), :data:`REQUIRED`, or a :class:`Derived` — a
default computed from other keys or from the record, which the reader computes and the text
describes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..errors import OptionError
from ..methods import ESTIMATION_METHODS

__all__ = ["AUTO_GAMMA_LAWS", "COLUMNS", "DATA", "DATA_RATE", "DATA_SIGNAL", "Derived",
           "ESTIMATOR", "Key", "LAWS", "PARAMETER_SET_BALL", "PARAMETER_SET_BOX",
           "PARAMETER_SET_ELLIPSOID", "PERTURBATION", "REQUIRED", "SCENARIO", "SCENARIO_HOLDS",
           "SCENARIO_METHODS", "SECOND", "STATE_SET", "SYSTEM", "TABLES", "TOP", "TYPES", "Table"]

#: The update laws of ``[estimator] law`` (Sec. IV).
LAWS = ("gradient", "least_squares", "algebraic", "intermittent")
#: The laws whose Γ defaults to ``"auto"`` (:mod:`~thetahat.estimation.observer.auto_gain`).
AUTO_GAMMA_LAWS = ("gradient", "least_squares")
#: Integrators a ``[scenario]`` may name (``scipy.integrate.solve_ivp`` methods).
SCENARIO_METHODS = ("Radau", "BDF", "LSODA", "RK45", "RK23", "DOP853")
#: How a ``[scenario]``'s input reaches its plant between samples (``u_hold``).
SCENARIO_HOLDS = ("continuous", "zoh")

#: The columns of every table, in order.
COLUMNS = ("section", "key", "type", "default", "example", "description")

#: The types of the ``type`` column and what a value of each looks like.
TYPES: dict[str, str] = {
    "string": "a string",
    "table": "a table",
    "matrix": "a nested list of rows of numbers, e.g. [[1.0, 0.0], [0.0, 1.0]]",
    "formula": "a formula string, or a list of them (one per component), never evaluated as "
               "code",
    "names": "a name, or a list of names",
    "numbers": "a list of numbers",
    "number": "a finite number",
    "positive number": "a finite number > 0",
    "non-negative number": "a finite number >= 0",
    "boolean": "true or false",
    "choice": "one of the listed strings",
    "poles": "a list of real poles < 0",
    "pole lists": "one list of real poles < 0 per chain",
    "positive number or auto": "a finite number > 0, or \"auto\"",
    "gain": "a positive number, a p × p symmetric positive-definite matrix, or \"auto\"",
    "constants": "a table of named numbers",
    "thresholds": "[low, high]",
    "tolerances": "a number > 0, or n numbers > 0",
    "sines": "a list of numbers (every input), or one list per input",
    "signal": "a column name, {column = NAME, scale = 1.0, offset = 0.0}, or a list of them "
              "(one per input or output)",
    "samples": "a segment's name, [START, STOP] (0-based sample indices, STOP excluded) or "
               "\"all\"",
    "segments": "a table of names to [START, STOP] (0-based sample indices, STOP excluded)",
}


@dataclass(frozen=True, slots=True)
class _Required:
    def __repr__(self) -> str:
        return "required"


#: The default of a key that must be given.
REQUIRED: Any = _Required()


@dataclass(frozen=True, slots=True)
class Derived:
    """A default computed from other keys or from the record.

    Parameters
    ----------
    how : str
        How it is computed, in words.

    Examples
    --------
    >>> Derived("the centre of Θ")
    Derived('the centre of Θ')
    """

    how: str

    def __repr__(self) -> str:
        return f"Derived({self.how!r})"


@dataclass(frozen=True, slots=True)
class Key:
    """One row of a section's table.

    Parameters
    ----------
    key : str
        The key's name in the file.
    type : str
        One of :data:`TYPES`.
    default : object
        The value the loader uses when the key is absent, :data:`REQUIRED`, or a
        :class:`Derived`.
    example : str
        A value, as written in a TOML file.
    description : str
        What it means.
    choices : tuple of str, optional
        The allowed values of a ``choice``.

    Examples
    --------
    >>> from thetahat.modelfile.keys import ESTIMATOR
    >>> ESTIMATOR["eps"].default, ESTIMATOR["law"].choices[0]
    (1.0, 'gradient')
    """

    key: str
    type: str
    default: Any
    example: str
    description: str
    choices: tuple[str, ...] = ()

    @property
    def required(self) -> bool:
        """The key must be given."""
        return self.default is REQUIRED

    @property
    def literal(self) -> bool:
        """The default is a value the loader uses as it is."""
        return not (self.required or isinstance(self.default, Derived))


@dataclass(frozen=True, slots=True)
class Table:
    """The keys of one section of a model file.

    Parameters
    ----------
    section : str
        ``"top level"``, ``"system"``, ``"estimator.second"``, ….
    keys : tuple of Key
        Its rows.
    form : str, optional
        Which form of the section (``[parameter_set]`` is a box, a ball or an ellipsoid;
        a signal of ``[data]`` a name or a table).
    note : str, optional
        What a form is, in a sentence, for the reference.

    Examples
    --------
    >>> from thetahat.modelfile.keys import SYSTEM
    >>> SYSTEM.names()
    ('A', 'B', 'C', 'E')
    >>> SYSTEM.rows()[0][:4]
    ('system', 'A', 'matrix', required)
    """

    section: str
    keys: tuple[Key, ...]
    form: str = ""
    note: str = ""

    def __post_init__(self) -> None:
        for k in self.keys:
            if k.type not in TYPES:
                raise OptionError(f"[{self.section}] {k.key}: unknown type {k.type!r}; "
                                  f"expected one of {list(TYPES)}.")

    def names(self) -> tuple[str, ...]:
        """The keys' names, in order.

        Returns
        -------
        tuple of str
        """
        return tuple(k.key for k in self.keys)

    def __getitem__(self, key: str) -> Key:
        """The row of ``key``."""
        for k in self.keys:
            if k.key == key:
                return k
        raise OptionError(f"[{self.section}] has no key {key!r}; its keys are "
                          f"{list(self.names())}.")

    def rows(self) -> tuple[tuple[Any, ...], ...]:
        """The table as rows of :data:`COLUMNS` (for the reference page).

        Returns
        -------
        tuple of tuple
            ``(section, key, type, default, example, description)`` per key.
        """
        return tuple((self.section, k.key, k.type, k.default, k.example, k.description)
                     for k in self.keys)


TOP = Table("top level", (
    Key("name", "string", Derived("the file's stem"), '"Oscillator (Proposition 3)"',
        "A title."),
    Key("system", "table", REQUIRED, "[system]", "The matrices of (1)."),
    Key("perturbation", "table", REQUIRED, "[perturbation]", "φ = g(v, x, θ) and the names."),
    Key("parameter_set", "table", REQUIRED, "[parameter_set]", "Θ, a convex set."),
    Key("state_set", "table", Derived("none: g as written for every x"), "[state_set]",
        "X, the box the states stay in: g is saturated outside it (Remark 1)."),
    Key("estimator", "table", REQUIRED, "[estimator]", "The gain design, the update law, the "
                                                       "initial values and the method."),
    Key("scenario", "table", Derived("every key's default"), "[scenario]",
        "The simulated experiment of `thetahat sweep` and `thetahat tune`."),
    Key("data", "table", Derived("the default column names"), "[data]",
        "Which variables or columns of a data file are t, u and y."),
))

SYSTEM = Table("system", (
    Key("A", "matrix", REQUIRED, "[[0.0, 1.0], [-1.0, -0.5]]", "A, n × n, eq. (1)."),
    Key("B", "matrix", REQUIRED, "[[0.0], [1.0]]", "B, n × m (`[]` when m = 0)."),
    Key("C", "matrix", REQUIRED, "[[1.0, 0.0]]", "C, r × n."),
    Key("E", "matrix", REQUIRED, "[[0.0], [1.0]]", "E, n × k."),
))

PERTURBATION = Table("perturbation", (
    Key("g", "formula", REQUIRED, '"(2 + sin(y))*(theta + theta**3/3)"',
        "φ = g(v, x, θ): one string (k = 1) or k strings, in the safe syntax of "
        "`thetahat.model.parse.parse_perturbation`."),
    Key("u", "names", REQUIRED, '["u"]', "The m input names (`[]` when m = 0)."),
    Key("y", "names", REQUIRED, '["y"]', "The r output names."),
    Key("x", "names", REQUIRED, '["x1", "x2"]', "The n state names."),
    Key("theta", "names", REQUIRED, '["theta"]', "The p parameter names."),
    Key("constants", "constants", {}, "{ sigma0 = 260.0 }",
        "Named numbers used in the formulas."),
))

_THETA_WHAT = "one number per parameter"
PARAMETER_SET_BOX = Table("parameter_set", (
    Key("lower", "numbers", REQUIRED, "[-2.0]", f"The lower corner of the box ({_THETA_WHAT})."),
    Key("upper", "numbers", REQUIRED, "[2.0]", f"The upper corner of the box ({_THETA_WHAT})."),
), form="a box", note="Θ = {θ : lower ≤ θ ≤ upper}, componentwise.")
PARAMETER_SET_BALL = Table("parameter_set", (
    Key("center", "numbers", REQUIRED, "[0.0, 0.0]", f"The centre ({_THETA_WHAT})."),
    Key("radius", "positive number", REQUIRED, "1.5",
        "The radius R: Θ = {θ : ‖θ − center‖ ≤ R}."),
), form="a ball", note="Θ = {θ : ‖θ − center‖ ≤ radius}.")
PARAMETER_SET_ELLIPSOID = Table("parameter_set", (
    Key("center", "numbers", REQUIRED, "[0.0, 0.0]", f"The centre ({_THETA_WHAT})."),
    Key("shape", "matrix", REQUIRED, "[[1.0, 0.0], [0.0, 4.0]]",
        "Q, p × p symmetric positive definite: Θ = {θ : (θ − center)ᵀ Q (θ − center) ≤ 1} "
        "(each eigenvalue is 1/a² for a semi-axis a)."),
), form="an ellipsoid",
   note="Θ = {θ : (θ − center)ᵀ Q (θ − center) ≤ 1}. A general convex set {P(θ) ≤ 0} needs a "
        "Python callable P and exists in the API only (thetahat.model.paramset.ConvexSet).")

_X_WHAT = "one number per state in [perturbation] x"
STATE_SET = Table("state_set", (
    Key("lower", "numbers", REQUIRED, "[0.0, -40.0]", f"The lower faces of X ({_X_WHAT})."),
    Key("upper", "numbers", REQUIRED, "[2.0, 80.0]", f"The upper faces of X ({_X_WHAT})."),
), note="X = {x : lower ≤ x ≤ upper}, finite. Every method then uses g(v, σ(x), θ), σ the "
        "identity on X and a smooth saturation outside it (thetahat.model.state_set): g is "
        "unchanged where the states are, and Lipschitz in x everywhere, as Assumption 2 needs "
        "of a g such as an Arrhenius rate or a cubic spring.")

_POLES_DEFAULT = Derived("−1, −2, … (thetahat.design.gains.high_gain)")
ESTIMATOR = Table("estimator", (
    Key("method", "choice", ESTIMATION_METHODS[0], '"guarded"',
        "How to estimate (thetahat.methods.METHODS).", choices=ESTIMATION_METHODS),
    Key("law", "choice", REQUIRED, '"gradient"',
        "The update law (8): gradient inversion (Props. 3–4), filtered least squares, "
        "algebraic inversion (Prop. 1) or intermittent inversion (Prop. 2, with the "
        "excitation weight smooth_ramp(*excitation) of ‖φ̂‖).", choices=LAWS),
    Key("eps", "positive number or auto", 1.0, "0.5",
        "ε of the modified high-gain design (Sec. VII); \"auto\": chosen on the record as the "
        "ε whose observer best predicts the next sample "
        "(thetahat.estimation.observer.auto_eps): `thetahat estimate` prints the ε it "
        "chose, and `thetahat codegen` takes it (--eps) or chooses it on a log (--data)."),
    Key("chain_poles", "pole lists", _POLES_DEFAULT, "[[-1.0, -2.0, -3.0]]",
        "The poles of each chain of the design."),
    Key("b_poles", "poles", _POLES_DEFAULT, "[-1.0, -2.0]", "The poles of A_b − K_bb C_b."),
    Key("Gamma", "gain", Derived('"auto" for the gradient and least-squares laws, 1 for the '
                                 'inversion laws'), "2.0",
        "Γ of the update law; \"auto\": chosen on the record from its information "
        "(thetahat.estimation.observer.auto_gain): `thetahat estimate` prints the Γ it "
        "chose, and `thetahat codegen` takes it (--gamma) or chooses it on a log (--data)."),
    Key("theta_hat0", "numbers", Derived("the centre of Θ"), "[0.0]", "θ̂(0), in Θ."),
    Key("x_hat0", "numbers", Derived("0"), "[0.0, 0.0]", "The prior of x̂(0)."),
    Key("x_hat0_from_y", "boolean", True, "false",
        "Start every method at x̂(0) = x̂₀ + C⁺(y(0) − C x̂₀), the state nearest x̂₀ that fits "
        "the record's first sample; false: at x̂₀."),
    Key("theta_star", "formula", Derived("solved from g with SymPy"), '"phi/(2 + sin(y))"',
        "θ*(v, x, φ) of the algebraic and intermittent laws, in the names of u, y, x and phi "
        "(k = 1) or phi1, …, phik; one string per parameter."),
    Key("excitation", "thresholds", Derived("required by the intermittent law"), "[0.5, 1.0]",
        "The thresholds on ‖φ̂‖ of the intermittent law's smooth excitation weight."),
    Key("on_invalid", "choice", "raise", '"freeze"',
        "What the algebraic and intermittent laws do where θ* is not finite.",
        choices=("raise", "freeze")),
    Key("A_design", "matrix", Derived("A"), "[[0.0, 1.0], [-1.0, 0.0]]",
        "A of a simplified design system the gains are designed on (Sec. VII–VIII)."),
    Key("E_design", "matrix", Derived("E"), "[[0.0], [1.0]]", "E of the design system."),
    Key("allow_nonminimum_phase", "boolean", False, "true",
        "Design even when Assumption 1 fails (to study the failure)."),
    Key("second", "table", Derived("no second observer"), "[estimator.second]",
        "The second observer of Sec. VI."),
))

SECOND = Table("estimator.second", (
    Key("eps2", "positive number", 1.0, "1.0", "ε of its high-gain design."),
    Key("chain_poles", "pole lists", _POLES_DEFAULT, "[[-1.0, -2.0]]",
        "The poles of each chain."),
    Key("b_poles", "poles", _POLES_DEFAULT, "[-1.0]", "The poles of A_b − K_bb C_b."),
    Key("g_on_estimates", "boolean", False, "true",
        "Evaluate g on C x̂₂ instead of the measured y (Sec. VIII)."),
))

SCENARIO = Table("scenario", (
    Key("theta", "numbers", Derived("half way from Θ's centre to its point nearest the upper "
                                    "corner of Θ's bounding box (a box: three quarters of "
                                    "the way from lower to upper)"), "[1.5]",
        "The true θ, in Θ."),
    Key("x0", "numbers", Derived("0"), "[0.0, 0.0]", "x(0) of the plant."),
    Key("t_end", "positive number", 20.0, "10.0", "The duration (s)."),
    Key("fs", "positive number", 100.0, "1000.0", "The sampling frequency (Hz)."),
    Key("noise_std", "non-negative number", 0.01, "0.02",
        "The standard deviation of the white noise on y."),
    Key("u_amplitudes", "sines", [1.0, 0.5], "[0.7, 0.25]",
        "The input u_i(t) = Σ_j a_ij sin(2π f_ij t): the amplitudes a_ij."),
    Key("u_frequencies", "sines", [0.1, 0.3], "[0.5, 1.3]",
        "The frequencies f_ij (Hz) of the input's sines."),
    Key("u_hold", "choice", "continuous", '"zoh"',
        "What drives the plant between samples: the sines themselves (continuous), or their "
        "samples at fs held by a DAC (zoh); sweep and tune then run the estimator with that "
        "hold.", choices=SCENARIO_HOLDS),
    Key("method", "choice", "Radau", '"LSODA"', "The integrator (scipy's solve_ivp).",
        choices=SCENARIO_METHODS),
    Key("rtol", "positive number", 1e-8, "1e-9", "Its relative tolerance."),
    Key("atol", "tolerances", 1e-10, "[1e-10, 1e-13]", "Its absolute tolerance(s)."),
))

DATA = Table("data", (
    Key("t", "signal", Derived("the column t"), '{ column = "time_ms", scale = 0.001 }',
        "The time in seconds: a column (a signal; a scale turns ms into s), or a time base "
        "{ rate = HZ, start = S } when the record has no time column."),
    Key("u", "signal", Derived("the inputs' names, or u1, u2, … (u when m = 1)"),
        '{ column = "vir", scale = 35.15 }',
        "The m inputs, in the order of [perturbation] u: one signal (m = 1) or a list of m."),
    Key("y", "signal", Derived("the outputs' names, or y1, y2, … (y when r = 1)"), '"qm"',
        "The r outputs, in the order of [perturbation] y: one signal (r = 1) or a list of r."),
    Key("samples", "samples", "all", '"train"',
        "The samples the estimators read (thetahat.io.mapping.select_samples): a segment of "
        "[data.segments] by name, [START, STOP], or \"all\"; `thetahat estimate --samples` "
        "overrides it. t keeps the file's values."),
    Key("segments", "segments", {}, '{ train = [0, 5000], test = [5000, 8000] }',
        "Named segments of the record, [START, STOP] each (0-based, STOP excluded): the "
        "training and test splits (thetahat.studies.validation scores θ̂ on the test ones)."),
))

#: One signal of ``[data]`` written as a table: ``value = scale · raw + offset``
#: (:class:`thetahat.io.mapping.Signal`; a bare name is ``{ column = NAME }``).
DATA_SIGNAL = Table("data", (
    Key("column", "string", REQUIRED, '"vir"',
        "The variable (MATLAB) or column (CSV, Parquet, Excel) of the data file."),
    Key("scale", "number", 1.0, "35.15",
        "The factor to the model's units (not 0): value = scale · raw + offset."),
    Key("offset", "number", 0.0, "-273.15", "Added after the scale."),
), form="a signal as a table",
   note="t, u and y (and each entry of a list of them) are each a name, \"qm\" (the same as "
        "{ column = \"qm\" }), or a table of these keys.")

#: ``[data] t`` as a time base, for a record without a time column:
#: t_k = start + k / rate (:func:`thetahat.io.mapping.parse_data_table`).
DATA_RATE = Table("data", (
    Key("rate", "positive number", REQUIRED, "1000.0", "The sampling rate (Hz)."),
    Key("start", "number", 0.0, "12.5", "t of the first sample (s)."),
), form="a time base for t",
   note="For a record without a time column: t = { rate = HZ }; the samples are at "
        "t_k = start + k / rate.")

#: Every table, in the order of a file.
TABLES: tuple[Table, ...] = (TOP, SYSTEM, PERTURBATION, PARAMETER_SET_BOX, PARAMETER_SET_BALL,
                             PARAMETER_SET_ELLIPSOID, STATE_SET, ESTIMATOR, SECOND, SCENARIO, DATA,
                             DATA_SIGNAL, DATA_RATE)
