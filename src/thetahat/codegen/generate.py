"""C99 code generation for a built observer: :func:`generate_c` and its result :class:`CCode`.

The generated pair ``<name>.h``/``<name>.c`` implements the step of
:class:`~thetahat.estimation.observer.ModifiedHighGainObserver` — observer (3), the update law
(8) with its projection onto Θ and excitation weight, and the second observer of Sec. VI — at a
fixed step dt and zero-order hold, in ``float`` or ``double``, with no heap, no recursion and no
global mutable state: the caller owns the state struct. The numbers come from the observer's
public objects (its matrices, gains, law and the discretisation ``observer.plan(dt)``); g,
∂g/∂x, ∂g/∂θ, ∂g/∂v and θ* are printed from their SymPy expressions by SymPy's C99 printer with
common-subexpression elimination (:mod:`.printing`); the stages of the step are those of the
Python step (:mod:`.c_step`).
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..errors import FileAccessError, UnsupportedError
from ..estimation.discretize import IMPLICITNESS
from ..estimation.observer import ModifiedHighGainObserver
from ..estimation.step import DIVERGENCE_BOUND
from ..estimation.theta_star import ThetaStar
from ..estimation.update_laws import (FAR, INIT_RTOL, ConstantLaw, GradientInversion,
                                      IntermittentInversion, SmoothRamp)
from ..model.paramset import Box
from ..model.perturbation import SymbolicPerturbation
from ..safe_io import write_text
from .c_step import StepOptions, step_source
from .harness import harness_source, makefile_source
from .printing import REALS, c_function

__all__ = ["CCode", "HOLDS", "discretisation", "generate_c", "generate_c_from_model",
           "model_hash"]

FloatArray = NDArray[np.float64]

#: Sample holds the generated step supports: the C step is causal, it sees only the current
#: samples, so the first-order hold (which interpolates to the next sample) is not available.
HOLDS = ("zoh",)
#: |θ̂| clip before the projection (update_laws.FAR in double; in float 1e30, below FLT_MAX, so
#: that the constant converts without overflow).
FAR_FLOAT = 1e30
#: The divergence rule's bound in float: step.DIVERGENCE_BOUND (1e100) is beyond FLT_MAX; 1e18
#: keeps its square (1e36) finite in float, far above any sensibly scaled observer quantity.
BOUND_FLOAT = 1e18

_LAWS: dict[type, str] = {ConstantLaw: "constant", IntermittentInversion: "intermittent",
         GradientInversion: "gradient"}


@dataclass(frozen=True, slots=True, repr=False)
class CCode:
    """Generated C sources of one observer (from :func:`generate_c`).

    Attributes
    ----------
    name : str
        File stem and C prefix: ``<name>.h``, ``<name>.c``, ``<name>_main.c``, ``<name>_init``...
    real : {"double", "float"}
    dt : float
        The fixed step length (s).
    header, source : str
        The dependency-free observer: ``<name>.h`` and ``<name>.c``.
    main, makefile : str
        The CSV harness ``<name>_main.c`` and the ``Makefile`` that builds ``<name>``.
    state_bytes : int
        ``sizeof(<name>_state)``: x̂, z, θ̂ (and x̂₂), all ``real``.
    const_bytes : int
        Bytes of the ``static const`` matrices and vectors of ``<name>.c``.
    sizes : dict
        (n, m, r, k, p) and the state length.
    """

    name: str
    real: str
    dt: float
    header: str
    source: str
    main: str
    makefile: str
    state_bytes: int
    const_bytes: int
    sizes: dict[str, int]

    def files(self) -> dict[str, str]:
        """File name → content of the four generated files."""
        return {f"{self.name}.h": self.header, f"{self.name}.c": self.source,
                f"{self.name}_main.c": self.main, "Makefile": self.makefile}

    def write(self, directory: str | Path) -> tuple[Path, ...]:
        """Write the four files into ``directory`` (created), each atomically; returns their
        paths.

        Raises
        ------
        FileAccessError
            The directory or a file cannot be written.
        """
        out = Path(directory)
        paths = []
        try:
            out.mkdir(parents=True, exist_ok=True)
            for fname, text in self.files().items():
                paths.append(write_text(out / fname, text))          # atomic, each file
        except OSError as exc:
            raise FileAccessError(f"cannot write the generated C into {out}: {exc}; choose a "
                                  "writable folder with -o.") from exc
        return tuple(paths)

    def summary(self) -> str:
        """One line per size, as ``thetahat codegen`` prints them."""
        word = 8 if self.real == "double" else 4
        return (f"{self.name}: n={self.sizes['n']} m={self.sizes['m']} r={self.sizes['r']} "
                f"k={self.sizes['k']} p={self.sizes['p']}, real={self.real}, dt={self.dt!r}\n"
                f"  sizeof({self.name}_state) = {self.state_bytes} bytes "
                f"({self.state_bytes // word} x {self.real})\n"
                f"  static const data         = {self.const_bytes} bytes "
                f"({self.const_bytes // word} x {self.real})")

    def __repr__(self) -> str:
        return (f"CCode(name={self.name!r}, real={self.real!r}, dt={self.dt!r}, "
                f"state_bytes={self.state_bytes}, const_bytes={self.const_bytes})")


def _c_name(name: str) -> str:
    ident = re.sub(r"\W", "_", name.strip(), flags=re.ASCII).lower()
    if not ident or ident[0].isdigit():
        ident = "obs_" + ident
    return ident


def _literal(value: float, real_type: str) -> str:
    if real_type == "double":
        return repr(float(value)) if value == value else "0"
    return f"{np.float32(value)}F"           # the shortest text that rounds to this float


def _array(name: str, values: ArrayLike, real_type: str, comment: str) -> tuple[str, int]:
    flat = np.asarray(values, dtype=np.float64).ravel()
    if flat.size == 0:
        flat = np.zeros(1)
    body = ", ".join(_literal(v, real_type) for v in flat)
    return (f"/* {comment} */\nstatic const real_t {name}[{flat.size}] = {{{body}}};\n",
            int(flat.size))


def _theta_star(law: Any, pert: SymbolicPerturbation
                ) -> tuple[tuple[sp.Expr, ...], tuple[sp.Symbol, ...]]:
    ts = law.theta_star
    form = (ts.expr, ts.arguments) if isinstance(ts, ThetaStar) else getattr(ts, "sympy_form",
                                                                              None)
    if form is None:
        raise UnsupportedError(
            f"the θ* of the {type(law).__name__} is a Python callable "
            f"({type(law.theta_star).__name__}); C needs its SymPy form: give θ* in the model "
            "file ([estimator] theta_star), or build the law with from_perturbation.")
    exprs, args = form
    n, m, r, p, k = pert.dims
    if len(exprs) != p or len(args) != m + r + n + k:
        raise UnsupportedError(f"θ* has {len(exprs)} entries in {len(args)} arguments; expected "
                           f"p = {p} entries of col(u, y), x, φ ({m + r + n + k} arguments).")
    return tuple(exprs), tuple(args)


def _check(observer: Any, hold: str, real: str) -> tuple[str, Any]:
    if not isinstance(observer, ModifiedHighGainObserver):
        raise UnsupportedError(f"generate_c needs a ModifiedHighGainObserver; got "
                           f"{type(observer).__name__}.")
    if hold not in HOLDS:
        raise UnsupportedError(f"hold {hold!r} is not available in C: the generated step is causal "
                           "(it sees the current samples only); use hold='zoh'.")
    if real not in REALS:
        raise UnsupportedError(f"real must be one of {REALS}; got {real!r}.")
    pert = observer.system.perturbation
    if not isinstance(pert, SymbolicPerturbation):
        raise UnsupportedError(f"g must be a SymbolicPerturbation (C is printed from its SymPy "
                           f"form); got {type(pert).__name__}.")
    # Any: the checks below read attributes (l, M, perturbation, Gamma) of several law classes.
    law: Any = observer.update_law
    kind = _LAWS.get(type(law))
    if kind == "intermittent" and law.l is None:        # AlgebraicInversion: l ≡ 1
        kind = "algebraic"
    if kind is None:
        raise UnsupportedError(f"the update law {type(law).__name__} has no C form; supported: "
                           "ConstantLaw, AlgebraicInversion, IntermittentInversion, "
                           "GradientInversion.")
    if observer.layout.law_size:
        raise UnsupportedError(f"the update law {type(law).__name__} has a state of its own; the C "
                           "step supports memoryless laws only.")
    if not isinstance(law.parameter_set, Box):
        raise UnsupportedError(f"Θ must be a Box (its projection is a clip); got "
                           f"{type(law.parameter_set).__name__}.")
    if getattr(law, "saturation", None) is not None:
        raise UnsupportedError("update laws with a saturation (Remark 3) have no C form yet; build "
                           "the law without saturation=.")
    if getattr(law, "layer", 0.0) != 0.0:
        raise UnsupportedError("only the hard projection (layer=0) has a C form.")
    G = np.asarray(getattr(law, "Gamma", np.eye(law.parameter_set.dim)))
    if not np.array_equal(G, np.diag(np.diag(G))):
        raise UnsupportedError("Γ must be diagonal: the Γ⁻¹-weighted projection onto a box is then "
                           "a clip (a full Γ needs a least-squares solve).")
    if kind == "intermittent" and not isinstance(law.l, SmoothRamp):
        raise UnsupportedError("the excitation weight must be smooth_ramp(low, high) of ‖φ̂‖; "
                           f"got {law.l!r}.")
    if kind == "gradient" and (law.M is not None or law.perturbation != pert):
        raise UnsupportedError("GradientInversion needs the default M = (∂g/∂θ)ᵀ and the "
                           "observer's own g.")
    return kind, law


def _model_functions(pert: SymbolicPerturbation, ts: Any, opts: StepOptions,
                     real: str) -> str:
    ins = [("v", (*pert.u, *pert.y)), ("x", pert.x), ("th", pert.theta)]
    g = sp.Matrix(pert.expr)
    funcs = [
        c_function("g_only", ins, [("g", g)], real),
        c_function("g_and_jacobians", ins, [("g", g), ("Gx", pert.jacobian("x")),
                                            ("Gth", pert.jacobian("theta"))], real),
    ]
    if opts.needs_dg_dv:
        funcs.append(c_function("g_dx_dv", ins, [("g", g), ("Gx", pert.jacobian("x")),
                                                 ("Gv", pert.jacobian("v"))], real))
    elif opts.second:
        funcs.append(c_function("g_and_dg_dx", ins, [("g", g), ("Gx", pert.jacobian("x"))],
                                real))
    if ts is not None:
        exprs, args = ts
        n, m, r, _, _ = pert.dims
        ts_ins = [("v", args[:m + r]), ("x", args[m + r:m + r + n]), ("phi", args[m + r + n:])]
        funcs.append(c_function("theta_star", ts_ins, [("ts", sp.Matrix(exprs))], real))
    return ("/* ---- g, dg/dx, dg/dtheta" + (", dg/dv" if opts.needs_dg_dv else "")
            + (", theta*" if ts is not None else "")
            + ": printed by SymPy's C99 printer with sympy.cse */\n"
            + "\n\n".join(funcs) + "\n")


def _inwards(lower: FloatArray, upper: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The float32 box closest to [lower, upper] that lies inside it."""
    lo, hi = np.asarray(lower, np.float32), np.asarray(upper, np.float32)
    lo = np.where(lo < lower, np.nextafter(lo, np.float32(np.inf)), lo)
    hi = np.where(hi > upper, np.nextafter(hi, np.float32(-np.inf)), hi)
    return lo.astype(np.float64), hi.astype(np.float64)


def discretisation(observer: ModifiedHighGainObserver, dt: float, *, predict: bool
                   ) -> dict[str, FloatArray]:
    """The φ-matrices the step uses, read from the observers' public plans (the one seam).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
    dt : float
        The fixed step length.
    predict : bool
        Also the plans of the prediction over a missing sample (``nan_policy="skip"``).

    Returns
    -------
    dict
        ``PHI1`` (and ``PHI1_OPEN``) of (3a)–(3b), ``PHI12`` (and ``PHI12_OPEN``) of the second
        observer when one is attached: Φ₁ = dt φ₁(dt L), shape (q, q).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> sorted(discretisation(build_observer(loads_model(EXAMPLE_MODEL)), 0.01, predict=False))
    ['PHI1', 'PHI12']
    """
    plan = observer.plan(dt)          # StepPlan: batch axis of length 1
    out = {"PHI1": plan.Phi1[0]}
    if predict:
        if plan.Phi1_open is None:
            raise UnsupportedError("predict=True needs the prediction plans, which the observer "
                                   "builds only with nan_policy='skip'.")
        out["PHI1_OPEN"] = plan.Phi1_open[0]
    if plan.second is not None:
        out["PHI12"] = plan.second.Phi1[0]
        if predict:
            if plan.second.Phi1_open is None:
                raise UnsupportedError("predict=True needs the second observer's prediction "
                                       "plans, built only with nan_policy='skip'.")
            out["PHI12_OPEN"] = plan.second.Phi1_open[0]
    return out


def _constants(observer: ModifiedHighGainObserver, law: Any, opts: StepOptions, dt: float,
               theta_hat0: FloatArray, x_hat0: FloatArray, real: str) -> tuple[str, int]:
    sysm = observer.system
    m = sysm.m
    B = sysm.B if m else np.zeros((sysm.n, 1))
    phi = discretisation(observer, dt, predict=opts.skip)
    arrays = [("A", sysm.A, "A of (1), n x n"), ("B", B, "B of (1), n x m"),
              ("C", sysm.C, "C of (1), r x n"), ("E", sysm.E, "E of (1), n x k"),
              ("KX", observer.K_x, "K_x(eps) of (3a), n x r"),
              ("KPHI", observer.K_phi, "K_phi(eps) of (3b), k x r"),
              ("KXC", observer.K_x @ sysm.C, "K_x C, n x n"),
              ("PHI1", phi["PHI1"],
               "Phi1 = dt phi1(dt L), L = [[A - K_x C, E], [-K_phi C, 0]] (discretize)")]
    if opts.skip:
        arrays.append(("PHI1_OPEN", phi["PHI1_OPEN"],
                       "Phi1 of L = [[A, E], [0, 0]] (prediction over a missing sample)"))
    if opts.second:
        if observer.second is None:
            raise UnsupportedError("the step options ask for a second observer but the observer "
                                   "has none attached.")
        arrays += [("K2", observer.second.K_x, "K_x of the second observer (Sec. VI), n x r"),
                   ("PHI12", phi["PHI12"], "Phi1 of A - K_x2 C (second observer)")]
        if opts.skip:
            arrays.append(("PHI12_OPEN", phi["PHI12_OPEN"],
                           "Phi1 of A (second observer, missing sample)"))
    box = law.parameter_set
    gamma = np.diag(np.asarray(getattr(law, "Gamma", np.eye(box.dim))))
    lower, upper = box.lower, box.upper
    if real == "float":             # rounded inwards: θ̂ stays in Θ in float too
        lower, upper = _inwards(lower, upper)
    arrays += [("THETA_LOWER", lower, "Theta = box [lower, upper]"),
               ("THETA_UPPER", upper, "Theta = box [lower, upper]")]
    if opts.law != "constant":
        arrays.append(("GAMMA", gamma, "diagonal of Gamma"))
    arrays += [("THETA_HAT0", theta_hat0, "default theta_hat(0)"),
               ("X_HAT0", x_hat0, "default x_hat(0)")]
    text, count = [], 0
    for name, values, comment in arrays:
        line, size = _array(name, values, real, comment)
        text.append(line)
        count += size
    scalars = [("DT", dt, "the fixed step length (s)"),
               ("IMPLICITNESS", IMPLICITNESS, "gamma of the linearly implicit step"),
               ("THETAHAT_FAR", FAR if real == "double" else FAR_FLOAT,
                "candidates are clipped to +-FAR before the projection"),
               ("INIT_RTOL", INIT_RTOL, "theta_hat0 may lie this far outside Theta"),
               ("DIVERGENCE_BOUND", DIVERGENCE_BOUND if real == "double" else BOUND_FLOAT,
                "the state has diverged when its norm exceeds this (step.DIVERGENCE_BOUND)")]
    if opts.law == "intermittent":
        scalars += [("RAMP_LOW", law.l.low, "excitation ramp: l = 0 below"),
                    ("RAMP_HIGH", law.l.high, "excitation ramp: l = 1 above")]
    for name, value, comment in scalars:
        text.append(f"static const real_t {name} = {_literal(value, real)}; /* {comment} */\n")
        count += 1
    return "".join(text), count


def model_hash(observer: ModifiedHighGainObserver) -> str:
    """SHA-256 of what defines the observer: g and θ* (srepr), the matrices, gains, law and Θ.

    Parameters
    ----------
    observer : ModifiedHighGainObserver

    Returns
    -------
    str
        64 hexadecimal digits.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> len(model_hash(build_observer(loads_model(EXAMPLE_MODEL))))
    64
    """
    h = hashlib.sha256()
    sysm, law = observer.system, observer.update_law
    # The hash is defined for the observers generate_c supports: a SymbolicPerturbation g and a
    # Box Θ (other observers fail here with AttributeError, as before; the casts only inform mypy).
    pert = cast(SymbolicPerturbation, sysm.perturbation)
    box = cast(Box, law.parameter_set)
    h.update(sp.srepr(pert.expr).encode())
    for arr in (sysm.A, sysm.B, sysm.C, sysm.E, observer.K_x, observer.K_phi,
                box.lower, box.upper,
                np.asarray(getattr(law, "Gamma", 0.0))):
        h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    h.update(repr((type(law).__name__, getattr(law, "on_invalid", None), observer.nan_policy,
                   getattr(law, "l", None) if hasattr(getattr(law, "l", None), "low") else None
                   )).encode())
    ts = getattr(law, "theta_star", None)
    form = (ts.expr, ts.arguments) if isinstance(ts, ThetaStar) else getattr(ts, "sympy_form",
                                                                              None)
    if form is not None:
        h.update(sp.srepr(form).encode())
    if observer.second is not None:
        h.update(np.ascontiguousarray(observer.second.K_x).tobytes())
        h.update(repr(observer.second.g_on_estimates).encode())
    return h.hexdigest()


def generate_c(observer: ModifiedHighGainObserver, *, dt: float, name: str = "observer",
               real: str = "double", hold: str = "zoh", theta_hat0: ArrayLike | None = None,
               x_hat0: ArrayLike | None = None, eps: float | None = None,
               model_sha256: str | None = None, title: str | None = None) -> CCode:
    """Generate a dependency-free C99 implementation of the observer's step at a fixed dt.

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        Observer (3) with its update law (8) and optional second observer (Sec. VI). Supported
        parts: a SymbolicPerturbation g; a Box Θ with diagonal Γ; ConstantLaw,
        AlgebraicInversion, IntermittentInversion (``smooth_ramp`` weight) with a θ* that has
        a SymPy form (from a model file or ``from_perturbation``), GradientInversion with the
        default M; no saturation; ``nan_policy`` "raise" or "skip".
    dt : float
        The fixed step length (s) > 0.
    name : str
        File stem and C prefix (made a C identifier).
    real : {"double", "float"}
        The C type of every number (``<name>_real_t``).
    hold : {"zoh"}
        Sample hold; the C step is causal.
    theta_hat0, x_hat0 : array_like, optional
        Defaults compiled in for ``<name>_init(s, NULL, NULL)``: ``update_law.init()`` and 0.
    eps : float, optional
        ε the gains were designed at, recorded in the header comment.
    model_sha256 : str, optional
        Hash recorded in the header (default :func:`model_hash` of the observer; the command
        line passes the model file's).
    title : str, optional
        Model title for the header comment.

    Returns
    -------
    CCode

    Raises
    ------
    UnsupportedError
        A part of the observer has no C form (the message names it).

    Notes
    -----
    The C step computes, in the same stages, what ``observer.step(state, u, y, dt)`` computes:
    the forcing of (3a)–(3b) with φ̂ = g + z (3c), the law's step and the projection onto Θ,
    the θ-term of (3b), the Jacobian part N, the second observer, then the linearly implicit
    exponential step with Φ₁ of ``observer.plan(dt)``. The state is committed only when it
    has not diverged (the rule of ``thetahat.estimation.step``: its norm is finite and at most
    ``DIVERGENCE_BOUND``, 1e18 in float); otherwise the step returns an error code and leaves
    it unchanged — the C form of the NonFiniteError / UpdateLawError the Python step raises. NaN in y follows
    ``nan_policy``, an invalid θ* ``on_invalid``. IEEE 754 arithmetic (C99 Annex F) is
    assumed, as on every target with an FPU; ``-ffast-math`` is refused.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> sorted(code.files())
    ['Makefile', 'prop3.c', 'prop3.h', 'prop3_main.c']
    >>> code.state_bytes                      # x̂ (2), z (1), θ̂ (1), x̂₂ (2) doubles
    48
    """
    from .. import __version__

    kind, law = _check(observer, hold, real)
    h = float(dt)
    if not (np.isfinite(h) and h > 0):
        raise UnsupportedError(f"dt must be a finite step length > 0; got {dt!r}.")
    prefix = _c_name(name)
    sysm = observer.system
    pert = cast(SymbolicPerturbation, sysm.perturbation)     # _check verified it
    n, m, r, p, k = pert.dims
    second = observer.second
    opts = StepOptions(prefix=prefix, law=kind, freeze=getattr(law, "on_invalid", "") == "freeze",
                       skip=observer.nan_policy == "skip", second=second is not None,
                       on_estimates=second is not None and second.g_on_estimates)
    ts = _theta_star(law, pert) if kind in ("algebraic", "intermittent") else None
    th0 = np.asarray(law.init(theta_hat0), dtype=np.float64).reshape(p)
    x0 = np.zeros(n) if x_hat0 is None else np.asarray(x_hat0, dtype=np.float64).reshape(n)
    consts, count = _constants(observer, law, opts, h, th0, x0, real)
    word = 8 if real == "double" else 4
    size = n + k + p + (n if second is not None else 0)
    info = {
        "model": title or "observer", "sha256": model_sha256 or model_hash(observer),
        "eps": "not recorded" if eps is None else repr(float(eps)), "dt": repr(h),
        "hold": hold, "law": type(law).__name__,
        "policy": (f"y NaN -> {observer.nan_policy}"
                   + (f"; theta* invalid -> {law.on_invalid}" if ts is not None else "")),
        "second": "none" if second is None else
        f"Sec. VI, g on {'estimates' if opts.on_estimates else 'y'}",
        "real": real, "version": __version__}
    header = _header(prefix, info, (n, m, r, k, p), real, opts)
    source = _source(prefix, info, real, consts, _model_functions(pert, ts, opts, real), opts)
    names = {"u": [s.name for s in pert.u], "y": [s.name for s in pert.y],
             "x": [s.name for s in pert.x], "theta": [s.name for s in pert.theta]}
    return CCode(name=prefix, real=real, dt=h, header=header, source=source,
                 main=harness_source(prefix, names, k, real, second is not None, h),
                 makefile=makefile_source(prefix), state_bytes=size * word,
                 const_bytes=count * word,
                 sizes={"n": n, "m": m, "r": r, "k": k, "p": p, "state": size})


def _banner(name: str, info: dict[str, str], what: str) -> str:
    return (f"/* {name} -- {what}\n"
            f" * Generated by thetahat {info['version']} (thetahat codegen); do not edit.\n *\n"
            " * The modified high-gain observer (3) with update law (8) of Grip, Saberi &\n"
            " * Johansen, discretised at a fixed step (exact exponential of the linear part,\n"
            " * linearly implicit correction for g).\n"
            f" *   model:      {info['model']}\n"
            f" *   sha256:     {info['sha256']}\n"
            f" *   eps:        {info['eps']}\n"
            f" *   dt:         {info['dt']} s\n"
            f" *   hold:       {info['hold']}\n"
            f" *   law:        {info['law']} (projection onto the box Theta)\n"
            f" *   second:     {info['second']}\n"
            f" *   policy:     {info['policy']}\n"
            f" *   real:       {info['real']}\n"
            f" *   thetahat:   {info['version']}\n */\n")


def _header(prefix: str, info: dict[str, str], dims: tuple[int, ...], real: str,
            opts: StepOptions) -> str:
    P, PU = prefix, prefix.upper()
    n, m, r, k, p = dims
    second_field = (f"    {P}_real_t x_hat_refined[{PU}_NX]; /* x_hat_2 of the second "
                    "observer (Sec. VI) */\n" if opts.second else "")
    second_access = (f"const {P}_real_t *{P}_x_hat_refined(const {P}_state *s);\n"
                     if opts.second else "")
    return (_banner(f"{P}.h", info, "interface") + f"""#ifndef {PU}_H
#define {PU}_H

typedef {real} {P}_real_t;

#define {PU}_NX {n} /* states x */
#define {PU}_NU {m} /* inputs u */
#define {PU}_NY {r} /* outputs y */
#define {PU}_NK {k} /* perturbation phi */
#define {PU}_NP {p} /* parameters theta */

/* Status codes of {P}_init, {P}_step and {P}_phi_hat ({P}_error_message explains them). On an
 * error the state is left unchanged. */
enum {{
    {PU}_OK = 0,
    {PU}_ERR_INPUT = 1,      /* u not finite, or y inf */
    {PU}_ERR_MISSING = 2,    /* y NaN under nan_policy 'raise' */
    {PU}_ERR_THETA_STAR = 3, /* theta* invalid where l > 0 under on_invalid 'raise' */
    {PU}_ERR_DIVERGED = 4,   /* the new state would diverge (norm > bound, NaN or inf) */
    {PU}_ERR_INIT = 5        /* theta_hat0 outside Theta, or not finite */
}};

/* The observer state, owned by the caller: col(x_hat, z, theta_hat[, x_hat_2]). */
typedef struct {P}_state {{
    {P}_real_t x_hat[{PU}_NX];     /* x_hat of (3a) */
    {P}_real_t z[{PU}_NK];         /* z of (3b): phi_hat = g(v, x_hat, theta_hat) + z (3c) */
    {P}_real_t theta_hat[{PU}_NP]; /* theta_hat of (8), always in Theta */
{second_field}}} {P}_state;

/* Start at theta_hat0 (in Theta) and x_hat0; NULL for the generated defaults. */
int {P}_init({P}_state *s, const {P}_real_t theta_hat0[], const {P}_real_t x_hat0[]);
/* Advance by dt holding the samples u[NU] (may be NULL when NU = 0) and y[NY]. */
int {P}_step({P}_state *s, const {P}_real_t u[], const {P}_real_t y[]);
/* phi_hat = g(v, x_hat, theta_hat) + z (3c) at the current samples. */
int {P}_phi_hat(const {P}_state *s, const {P}_real_t u[], const {P}_real_t y[],
{' ' * (len(P) + 12)}{P}_real_t phi_hat[]);
const {P}_real_t *{P}_x_hat(const {P}_state *s);
const {P}_real_t *{P}_theta_hat(const {P}_state *s);
{second_access}const char *{P}_error_message(int status);

#endif /* {PU}_H */
""")


def _source(prefix: str, info: dict[str, str], real: str, consts: str, model: str,
            opts: StepOptions) -> str:
    P, PU = prefix, prefix.upper()
    suffix = "" if real == "double" else "f"
    return (_banner(f"{P}.c", info, "implementation (C99, <math.h> only, no heap)")
            + f"""#include "{P}.h"

#include <math.h>

#if defined(__FAST_MATH__)
#error "compile without -ffast-math: the NaN and overflow policy needs IEEE isfinite()"
#endif

typedef {P}_real_t real_t;

#define NX {PU}_NX
#define NU {PU}_NU
#define NY {PU}_NY
#define NK {PU}_NK
#define NP {PU}_NP
#define NZ (NX + NK)
#define NV (NU + NY)
#define NUB (NU > 0 ? NU : 1)
#define EXP exp{suffix}
#define SQRT sqrt{suffix}
#define FABS fabs{suffix}

/* ---- constants: matrices row-major, the discretisation for the fixed dt */
{consts}
{model}{step_source(opts)}""")


def generate_c_from_model(path: str | Path, *, dt: float, eps: float | None = None,
                          real: str = "double", name: str | None = None) -> CCode:
    """:func:`generate_c` for the estimator of a model file (``thetahat codegen``).

    Parameters
    ----------
    path : str or Path
        Model file (.toml or .json).
    dt : float
        The fixed step length (s).
    eps : float, optional
        Overrides ``[estimator] eps``.
    real : {"double", "float"}
    name : str, optional
        File stem and C prefix; default the model file's stem.

    Returns
    -------
    CCode
        With the file's θ̂(0) and x̂(0) as defaults and the SHA-256 of the file's bytes in the
        header.

    Raises
    ------
    ModelFileError
        The file cannot be read or is invalid.
    UnsupportedError
        A part of the estimator has no C form.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "prop3.toml"
    >>> _ = path.write_text(EXAMPLE_MODEL)
    >>> generate_c_from_model(path, dt=0.01).name
    'prop3'
    """
    from ..modelfile import build_observer, load_model

    spec = load_model(path)
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    observer = build_observer(spec, eps=eps)
    return generate_c(observer, dt=dt, name=name or Path(path).stem, real=real,
                      theta_hat0=spec.estimator.theta_hat0, x_hat0=spec.estimator.x_hat0,
                      eps=spec.estimator.eps if eps is None else eps, model_sha256=digest,
                      title=spec.name)
