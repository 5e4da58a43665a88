"""The C step derived from the formulas: what :func:`~thetahat.codegen.generate_c` compiles.

:func:`derived_step` prints, with :class:`~thetahat.codegen.c_printer.CUnit`, the step's
formulas (:mod:`~thetahat.estimation.observer.formulas`,
:mod:`~thetahat.estimation.observer.laws.formulas`, the scalar functions of the vocabulary and
the law's hooks: the program of :func:`~thetahat.estimation.observer.kernel_source.kernel_program`,
printed for the ``"scalar"`` target as the numba kernel is) specialised for one observer:
the dimensions, the hold, the second observer, the law's options and the step length are
constants; the plan's matrices (:func:`~thetahat.estimation.observer.kernel_data.kernel_arrays`, the
numba kernel's data) are ``static const`` arrays; the arrays a formula writes are buffers on
the stack of ``<name>_step``. g, its Jacobians and θ* are printed from SymPy
(:mod:`.printing`). Around it a small C API (``<name>_init``, ``<name>_step``,
``<name>_phi_hat``, the accessors and the status messages) is written here.

The step of a measured sample and the prediction over a missing one (``nan_policy="skip"``)
are two specialisations of ``advance`` (``correct`` is a constant in each), so each prints
only its own branch.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy as sp

from ..errors import UnsupportedError
from ..estimation.kernels import scalar_primitives
from ..estimation.kernels.kernel_args import SHAPES, WorkArrays, dimensions
from ..estimation.observer.kernel_data import KernelParts, kernel_arrays
from ..estimation.observer.discretize import IMPLICITNESS
from ..estimation.observer.formulas import DIVERGENCE_BOUND
from ..estimation.observer.laws.base import FAR
from ..estimation.observer.plan import StepPlan
from ..estimation.observer.kernel_source import LAWS, kernel_program
from ..estimation.status import status_constants
from ..model.perturbation import SymbolicPerturbation
from .c_printer import CUnit
from .c_values import Arr, Const, Scal, real_literal
from .printing import c_function

__all__ = ["BOUND_FLOAT", "FAR_FLOAT", "DerivedStep", "derived_step", "inwards",
           "printed_functions"]

#: |θ̂| clip before the projection in float (law_base.FAR is 1e300 in double): below FLT_MAX,
#: so that the constant converts without overflow.
FAR_FLOAT = 1e30
#: The divergence bound in float: formulas.DIVERGENCE_BOUND (1e100) is beyond FLT_MAX; 1e18
#: keeps its square (1e36) finite in float, far above any sensibly scaled observer quantity.
BOUND_FLOAT = 1e18

#: Per law formula, the LAW_i arrays its formulas write (scratch, found by printing): the next
#: observer with that law is printed once.
_SCRATCH: dict[str, frozenset[str]] = {}

#: Names of the plan tuples' arrays in the generated C (formulas' module docstring).
_P_NAMES = ("L", "BV", "E", "C", "A", "B", "KX", "KXC", "PHI1", "PHI2")
_P2_NAMES = ("A", "B", "C", "E", "KX", "PHI1", "PHI2")

@dataclass(frozen=True)
class DerivedStep:
    """The printed parts of a derived C step.

    Attributes
    ----------
    constants : str
        ``static const`` definitions of the arrays and scalars the code reads.
    functions : str
        Model functions and specialised formulas.
    step_buffers, step_calls : str
        The work buffers of ``<name>_step`` (C declarations) and its calls of the formulas,
        which return the status or fall through with the new state in ``next``.
    phi_buffers, phi_calls : str
        The same for ``<name>_phi_hat``.
    const_count : int
        Numbers in the constants (for the size summary).
    """

    constants: str
    functions: str
    step_buffers: str
    step_calls: str
    phi_buffers: str
    phi_calls: str
    const_count: int


#: The formulas the C API calls: the step, the divergence rule and φ̂ at a sample.
_ROOTS = ("advance", "within_bound", "readout")


def printed_functions(law: str) -> dict[str, ast.FunctionDef]:
    """The functions of the C step of a law formula, printed for the scalar target, by name
    (``law_step``: the law formula).

    Parameters
    ----------
    law : str
        A value of :data:`~thetahat.estimation.observer.kernel_source.LAWS`.

    Returns
    -------
    dict of str to ast.FunctionDef
        Read-only trees (shared with every caller).

    Examples
    --------
    >>> fns = printed_functions("held_law")
    >>> fns["law_step"] is fns["held_law"], [a.arg for a in fns["implicit_step"].args.args][7:]
    (True, ['s', 's_at', 'out', 'out_at', 'M', 'rhs'])
    """
    program = kernel_program(law)
    out = {name: program.printed(name, "scalar")
           for name in program.closure([*_ROOTS, *scalar_primitives.SCALAR_PRIMITIVES])}
    out["law_step"] = out[law]
    return out


#: Model functions: C name, input arrays (by argument position, offset position) and the
#: output arguments' positions.
_MODEL = {
    "g_val": ((0, None), (1, 2), (3, 4)),
    "g_dx": ((0, None), (1, 2), (3, 4)),
    "dg_dy": ((0, None), (1, 2), (3, 4)),
    "dg_dtheta": ((0, None), (1, 2), (3, 4)),
    "theta_star": ((0, None), (1, 2), (3, None)),
}


def _pointer(arr: Any, offset: Any) -> str:
    if not isinstance(arr, Arr):
        raise UnsupportedError(f"a model function needs arrays; got {arr!r}")
    if offset is None or (isinstance(offset, Const) and offset.value == 0):
        return arr.name
    if isinstance(offset, Const):
        return f"{arr.name} + {offset.value}"
    raise UnsupportedError("a model function's offset must be a constant")


def _model_text(pert: SymbolicPerturbation, ts: tuple[Any, Any] | None, used: set[str],
                real: str) -> str:
    ins = [("v", (*pert.u, *pert.y)), ("x", pert.x), ("th", pert.theta)]
    n, m, r, _, _ = pert.dims
    g = sp.Matrix(pert.expr)
    Gv = pert.jacobian("v")
    outs = {"g_val": [("g", g)], "g_dx": [("g", g), ("Gx", pert.jacobian("x"))],
            "dg_dy": [("Gy", Gv[:, m:m + r])], "dg_dtheta": [("Gth", pert.jacobian("theta"))]}
    parts = []
    for name in ("g_val", "g_dx", "dg_dy", "dg_dtheta"):
        if name in used:
            parts.append(c_function(name, ins, outs[name], real))
    if "theta_star" in used:
        if ts is None:
            raise UnsupportedError("the law calls θ* but the observer has none")
        exprs, args = ts
        ts_ins = [("v", args[:m + r]), ("x", args[m + r:m + r + n]), ("phi", args[m + r + n:])]
        parts.append(c_function("theta_star", ts_ins, [("ts", sp.Matrix(exprs))], real))
    return "\n\n".join(parts) + ("\n" if parts else "")


def inwards(lower: Any, upper: Any) -> tuple[Any, Any]:
    """The float32 box closest to [lower, upper] that lies inside it (θ̂ stays in Θ in float).

    Parameters
    ----------
    lower, upper : array_like

    Returns
    -------
    lower, upper : ndarray
        float64 arrays of float32 values.

    Examples
    --------
    >>> lo, hi = inwards([0.7], [0.7000001])
    >>> bool(lo[0] >= 0.7 and hi[0] <= 0.7000001)
    True
    """
    lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    lo, hi = lower.astype(np.float32), upper.astype(np.float32)
    lo = np.where(lo < lower, np.nextafter(lo, np.float32(np.inf)), lo)
    hi = np.where(hi > upper, np.nextafter(hi, np.float32(-np.inf)), hi)
    return lo.astype(np.float64), hi.astype(np.float64)


def derived_step(parts: KernelParts, plan: StepPlan, *, prefix: str, real: str, foh: bool,
                 skip: bool, dt: float, theta_star: tuple[Any, Any] | None,
                 extra: dict[str, Any]) -> DerivedStep:
    """Print the step of one observer as C (see the module docstring).

    Parameters
    ----------
    parts : KernelParts
        The observer's checked parts (:func:`~thetahat.estimation.observer.kernel_data.kernel_parts`).
    plan : StepPlan
        The observer's plan for the fixed step.
    prefix : str
        C prefix of the status codes.
    real : {"double", "float"}
    foh : bool
        First-order hold: the step also takes the next samples.
    skip : bool
        ``nan_policy="skip"``: predict over a missing sample.
    dt : float
        The step length (the constant ``DT``).
    theta_star : (exprs, arguments) or None
        θ*'s SymPy form for the inversion laws.
    extra : dict of str to array
        Further constants the API reads (THETA_LOWER, THETA_HAT0, …); printed if used.

    Returns
    -------
    DerivedStep

    Raises
    ------
    UnsupportedError
        A formula leaves the printable subset, or θ*/g cannot be printed in C.
    """
    lay = plan.layout
    n, m, r, k, p = lay.n, lay.m, lay.r, lay.k, lay.p
    P, P2, LP, flags = kernel_arrays(parts, plan)
    kinds = (type(P), type(P2), type(LP))     # named tuples stay named (attribute access)
    second, on_est = bool(flags[0]), bool(flags[1])
    law = LAWS[parts.code]
    if real == "float":             # rounded inwards: θ̂ stays in Θ in float too
        lo, hi = inwards(LP.lower, LP.upper)
        LP = LP._replace(lower=lo, upper=hi)
    opts_at = LP._fields.index("opts")
    data: dict[str, Any] = {}

    def named(prefix: str, names: Sequence[str], arrays: Sequence[Any]) -> list[str]:
        out = []
        for name, a in zip(names, arrays):
            key = f"{prefix}_{name}"
            data[key] = np.asarray(a, dtype=np.float64)
            out.append(key)
        return out

    plans = {True: (named("PLAN", _P_NAMES, P), named("SECOND", _P2_NAMES, P2))}
    if skip:
        open1 = plan.Phi1_open[0] if plan.Phi1_open is not None else None
        open2 = plan.Phi2_open[0] if plan.Phi2_open is not None else None
        if open1 is None or open2 is None:
            raise UnsupportedError("nan_policy='skip' needs the plan's prediction matrices")
        pn = named("PLAN", _P_NAMES, P)
        pn[8:10] = named("PLAN", ("PHI1_OPEN", "PHI2_OPEN"), (open1, open2))
        p2n = named("SECOND", _P2_NAMES, P2)
        if plan.second is not None:
            s1, s2 = plan.second.Phi1_open, plan.second.Phi2_open
            if s1 is None or s2 is None:
                raise UnsupportedError("nan_policy='skip' needs the second observer's "
                                       "prediction matrices")
            p2n[5:7] = named("SECOND", ("PHI1_OPEN", "PHI2_OPEN"), (s1[0], s2[0]))
        plans[False] = (pn, p2n)
    options = None
    if law == "inversion_law":
        options = tuple(Const(float(v)) for v in LP.opts)
    # the law's arrays by field; a field this binding leaves None has no C array
    lp_names: list[str | None] = [None if a is None else f"LAW_{f.upper()}"
                                  for f, a in zip(LP._fields, LP)]
    for name, a in zip(lp_names, LP):
        if name is not None:
            data[name] = np.asarray(a, dtype=np.float64)
    data.update({k_: np.asarray(v, dtype=np.float64) for k_, v in extra.items()})
    ts = theta_star
    far = FAR if real == "double" else FAR_FLOAT
    bound = DIVERGENCE_BOUND if real == "double" else BOUND_FLOAT
    dims = dimensions(n, m, r, k, p, 0)
    constants: dict[str, Any] = {name: Const(v) for name, v in dims.items()}
    constants.update({"IMPLICITNESS": Const(IMPLICITNESS, "IMPLICITNESS"),
                      "FAR": Const(far, "THETAHAT_FAR"),
                      "EXP_TINY_ARG": Const(scalar_primitives.EXP_TINY_ARG, "EXP_TINY_ARG"),
                      "BOUND_SQ": Const(bound * bound, "BOUND_SQ"), "USER_M": Const(False)})
    constants.update({name: Const(code) for name, code in status_constants().items()})
    functions = printed_functions(law)
    size = lay.size
    scratch = set(_SCRATCH.get(law, ()))
    for _ in range(2):
        step, written = _print(functions, constants, data, scratch, plans, lp_names, options,
                               opts_at, set(extra), kinds=kinds,
                          pert=parts.perturbation, ts=ts, prefix=prefix,
                          real=real, foh=foh, dt=dt,
                          skip=skip, second=second, on_est=on_est, size=size,
                          dims=dims, scalars={"IMPLICITNESS": IMPLICITNESS,
                                              "THETAHAT_FAR": far, "BOUND_SQ": bound * bound,
                                              "DT": dt,
                                              "EXP_TINY_ARG": scalar_primitives.EXP_TINY_ARG})
        if not written:
            _SCRATCH[law] = frozenset(scratch)
            return step
        if not written <= set(data) - scratch:
            raise UnsupportedError(f"the C printer cannot write {sorted(written)}")
        scratch |= written
    raise UnsupportedError("the C printer did not settle the scratch arrays")  # pragma: no cover


def _print(functions: dict[str, ast.FunctionDef], constants: dict[str, Any],
           data: dict[str, Any], scratch: set[str], plans: dict[bool, Any],
           lp_names: list[str | None], options: Any, opts_at: int, extra: set[str], *,
           kinds: tuple[type, type, type], pert: SymbolicPerturbation, ts: Any, prefix: str,
           real: str, foh: bool,
           dt: float, skip: bool,
           second: bool, on_est: bool, size: int, dims: dict[str, int],
           scalars: dict[str, float]) -> tuple[DerivedStep, set[str]]:
    def arr(name: str) -> Arr:
        a = data[name]
        if name in scratch:
            return Arr(name.lower(), a.shape)
        return Arr(name, a.shape, glob=True)

    def model(name: str, args: Sequence[Any] | None) -> tuple[str, list[str]] | None:
        spec = _MODEL.get(name)
        if spec is None:
            return None
        if args is None:
            return name, []
        used_inputs = {a for a, _ in spec} | {o for _, o in spec if o is not None}
        texts = [_pointer(args[a], None if o is None else args[o]) for a, o in spec]
        for i, value in enumerate(args):
            if i in used_inputs:
                continue
            if isinstance(value, Arr) and value.glob:
                unit.written_globals.add(value.name)
            texts.append(_pointer(value, None))
        return name, texts

    unit = CUnit(functions, constants, model, real)
    lp: list[Any] = [None if name is None else arr(name) for name in lp_names]
    if options is not None:
        lp[opts_at] = options
    LP = _like(kinds[2], lp)
    shapes = SHAPES["WorkArrays"]
    W = WorkArrays(*(Arr(f"w_{name}", tuple(dims[d] for d in shapes[name]))
                     for name in WorkArrays._fields))
    nub = max(dims["NU"], 1)
    s, nxt = Arr("s", (size,)), Arr("next", (size,))
    u0, y0 = Arr("u0", (nub,)), Arr("y0", (dims["NY"],))
    u1, y1 = (Arr("u1", (nub,)), Arr("y1", (dims["NY"],))) if foh else (u0, y0)
    dtc = Const(dt, "DT")
    calls = {}
    for correct, (pn, p2n) in plans.items():
        P = _like(kinds[0], [arr(x) for x in pn])
        P2 = _like(kinds[1], [arr(x) for x in p2n])
        calls[correct] = unit.call("advance", [P, P2, LP, s, u0, y0, u1, y1, dtc, Const(correct),
                                               Const(foh), Const(second), Const(on_est), nxt, W])
    bound = unit.call("within_bound", [nxt, Const(size)])
    C = arr(plans[True][0][3])
    phi = unit.call("readout", [C, s, u0, y0, Scal("correct", "int"), W[0], W[1],
                                Arr("phi_hat", (dims["NK"],))])
    model_text = _model_text(pert, ts, unit.model_calls, real)
    functions_text = model_text + "\n" + unit.source()

    def call(fn: Any) -> str:
        return f"{fn.name}({', '.join(fn.args)})"

    PU = prefix.upper()
    if skip:
        advance = (f"    status = correct ? {call(calls[True])}\n"
                   f"                     : {call(calls[False])};\n")
    else:
        advance = f"    status = {call(calls[True])};\n"
    step_calls = advance + (
        "    if (status != 0) {\n"              # the formulas' codes are the header's
        "        return status;\n    }\n"
        f"    if (!{call(bound)}) {{\n        return {PU}_ERR_DIVERGED;\n    }}\n")
    phi_calls = f"    {call(phi)};\n"
    buffers = [*W, *(arr(x) for x in sorted(scratch))]

    def declare(text: str) -> str:
        names = _tokens(text)
        return "".join(f"    real_t {b.name}[{max(b.size, 1)}];\n" for b in buffers
                       if b.name in names)

    step_buffers, phi_buffers = declare(step_calls), declare(phi_calls)
    body = step_buffers + step_calls + phi_buffers + phi_calls
    tokens = _tokens(functions_text + body)
    const_lines, count = [], 0
    for name, a in data.items():
        if name in scratch or (name not in tokens and name not in extra):
            continue
        if a.ndim == 0:
            const_lines.append(f"static const real_t {name} = {real_literal(a, real)};")
            count += 1
            continue
        flat = a.ravel() if a.size else np.zeros(1)
        body = ", ".join(real_literal(v, real) for v in flat)
        const_lines.append(f"static const real_t {name}[{flat.size}] = {{{body}}};")
        count += flat.size
    for name, value in scalars.items():
        if name in tokens:
            const_lines.append(f"static const real_t {name} = {real_literal(value, real)};")
            count += 1
    return DerivedStep(constants="\n".join(const_lines) + "\n", functions=functions_text,
                       step_buffers=step_buffers, step_calls=step_calls,
                       phi_buffers=phi_buffers, phi_calls=phi_calls,
                       const_count=count), unit.written_globals


def _like(kind: type, items: Sequence[Any]) -> tuple[Any, ...]:
    """``items`` as a tuple of ``kind`` (a named tuple type keeps its field names)."""
    return kind(*items) if hasattr(kind, "_fields") else tuple(items)


def _tokens(text: str) -> set[str]:
    import re
    return set(re.findall(r"[A-Za-z_]\w*", text))
