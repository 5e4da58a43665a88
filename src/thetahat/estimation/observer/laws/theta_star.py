"""θ*(v, x, φ): the solution of φ = g(v, x, θ) for θ (Propositions 1–2), as one object.

A :class:`ThetaStar` carries the SymPy expression of the inverse and the numpy function
lambdified from it, so that every back end — the Python step, the batched runs, the compiled
kernel and code generators — evaluates the same formula: there is nothing to reconcile.
Build it from an expression in g's symbols (:meth:`ThetaStar.from_expr`) or let SymPy solve
φ = g(v, x, θ) (:meth:`ThetaStar.solve`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, final

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from .... import limits
from ....errors import DimensionError, UpdateLawError
from ....model.paramset import ParameterSet
from ....model.jacobian_check import require_theta_dependence
from ....model.lambdify import lambdify_numpy
from ....model.perturbation import Perturbation, SymbolicPerturbation

__all__ = ["ThetaStar", "SOLVE_RTOL", "SOLVE_SAMPLES", "as_theta_star"]

FloatArray = NDArray[np.float64]

#: Relative accuracy with which a θ* derived by SymPy must recover θ from φ = g(v, x, θ) at the
#: random check points (the expressions are exact, so this only absorbs rounding); also the
#: relative size of an imaginary part that counts as rounding of a real value.
SOLVE_RTOL = 1e-6
#: Number of random points used to tell the right branch of a SymPy solution from the others.
SOLVE_SAMPLES = 32


@final
@dataclass(frozen=True, slots=True, eq=False)
class ThetaStar:
    """θ*(v, x̂, φ̂) as a SymPy expression and its lambdified numerics.

    Parameters
    ----------
    expr : tuple of sympy.Expr
        The p entries of θ*.
    arguments : tuple of sympy.Symbol
        The symbols of col(u, y), then x, then φ, in call order (m + r + n + k of them).
    sizes : (int, int, int)
        (m + r, n, k): how ``arguments`` splits into v, x and φ.

    Attributes
    ----------
    fn : callable
        The numpy function of the arguments (one array per symbol).

    Notes
    -----
    Calling it evaluates θ* for arrays ``v (..., m + r)``, ``x (..., n)``, ``phi (..., k)``
    and returns ``(..., p)``; points where θ* is undefined (division by zero, a complex
    value, overflow) give NaN, which the update laws treat as invalid there.

    Examples
    --------
    >>> import sympy as sp
    >>> from thetahat.model.perturbation import SymbolicPerturbation
    >>> u, y, x, th, phi = sp.symbols("u y x theta phi", real=True)
    >>> g = SymbolicPerturbation(expr=[sp.sinh(th) * (1 + x**2)], u=[u], y=[y], x=[x],
    ...                          theta=[th])
    >>> ts = ThetaStar.from_expr(sp.asinh(phi / (1 + x**2)), perturbation=g, phi=[phi])
    >>> ts
    ThetaStar(asinh(phi/(x**2 + 1)))
    >>> round(float(ts([0.0, 0.0], [1.0], [2 * float(sp.sinh(0.3))])[0]), 12)
    0.3
    """

    expr: tuple[sp.Expr, ...]
    arguments: tuple[sp.Symbol, ...]
    sizes: tuple[int, int, int]
    fn: Callable[..., Any] = field(repr=False)

    def __init__(self, *, expr: Sequence[Any], arguments: Sequence[sp.Symbol],
                 sizes: tuple[int, int, int]) -> None:
        try:
            exprs = tuple(sp.sympify(e, strict=True) for e in expr)
        except (sp.SympifyError, TypeError) as exc:
            raise UpdateLawError(f"ThetaStar: expr must be SymPy expressions; got "
                                 f"{expr!r}.") from exc
        args = tuple(arguments)
        if len(args) != sum(sizes) or not all(isinstance(a, sp.Symbol) for a in args):
            raise DimensionError(f"ThetaStar: arguments must be {sum(sizes)} SymPy symbols "
                                 f"(v, x, φ); got {len(args)}.")
        free = set().union(*(e.free_symbols for e in exprs)) if exprs else set()
        if free - set(args):
            raise UpdateLawError(f"ThetaStar: the expression uses unknown symbols "
                                 f"{sorted(map(str, free - set(args)))}; it may use g's u, y, x "
                                 "and the φ symbols only.")
        fn = lambdify_numpy(args, exprs)
        object.__setattr__(self, "expr", exprs)
        object.__setattr__(self, "arguments", args)
        object.__setattr__(self, "sizes", tuple(int(s) for s in sizes))
        object.__setattr__(self, "fn", fn)

    def __reduce__(self) -> tuple[Any, ...]:
        # The lambdified function does not pickle (worker processes of a study need it to);
        # rebuild it from the expression.
        return (_rebuild_theta_star, (self.expr, self.arguments, self.sizes))

    @classmethod
    def from_expr(cls, expr: Any, *, perturbation: SymbolicPerturbation,
                  phi: Sequence[sp.Symbol] | sp.Symbol) -> ThetaStar:
        """θ* written in the symbols of a SymbolicPerturbation and k symbols for φ.

        Parameters
        ----------
        expr : sympy.Expr or sequence of p of them
            θ*(v, x, φ); must not depend on θ.
        perturbation : SymbolicPerturbation
            The g whose inverse it is (its u, y, x symbols are the arguments).
        phi : sympy.Symbol or sequence of k of them
            The symbols standing for φ, in order.

        Returns
        -------
        ThetaStar

        Raises
        ------
        DimensionError
            Wrong number of entries or φ symbols.
        UpdateLawError
            The expression uses θ or unknown symbols.
        """
        if not isinstance(perturbation, SymbolicPerturbation):
            raise UpdateLawError("ThetaStar.from_expr needs a SymbolicPerturbation (its "
                                 f"symbols); got {type(perturbation).__name__}.")
        n, m, r, p, k = perturbation.dims
        entries = list(expr) if isinstance(expr, (list, tuple, sp.MatrixBase)) else [expr]
        if len(entries) != p:
            raise DimensionError(f"ThetaStar: θ* must have p = {p} entries; got "
                                 f"{len(entries)}.")
        phis = (phi,) if isinstance(phi, sp.Symbol) else tuple(phi)
        if len(phis) != k:
            raise DimensionError(f"ThetaStar: phi must be k = {k} symbol(s); got {phi!r}.")
        if set().union(*(sp.sympify(e).free_symbols for e in entries)) & set(perturbation.theta):
            raise UpdateLawError("ThetaStar: θ* must not depend on θ (it is the solution "
                                 "θ*(v, x, φ) of φ = g(v, x, θ)).")
        args = (*perturbation.u, *perturbation.y, *perturbation.x, *phis)
        return cls(expr=entries, arguments=args, sizes=(m + r, n, k))

    @classmethod
    def solve(cls, perturbation: Perturbation, parameter_set: ParameterSet, *,
              seed: int = 0) -> ThetaStar:
        """θ* from ``sympy.solve`` of φ = g(v, x, θ), keeping the branch that inverts g on Θ.

        Among SymPy's solutions, the one branch that recovers θ from φ = g(v, x, θ) at random
        points (θ ∈ Θ drawn with ``seed``, v and x standard normal) is kept; of its raw and
        expanded forms, the one finite at more of those points.

        Parameters
        ----------
        perturbation : SymbolicPerturbation
        parameter_set : ParameterSet
            Θ, where the inverse must be unique.
        seed : int
            Seed of the check points.

        Returns
        -------
        ThetaStar

        Raises
        ------
        UpdateLawError
            g does not depend on θ, SymPy cannot solve, or not exactly one branch inverts g
            (the solution is not unique): pass θ* yourself or use GradientInversion.
        SymbolicTimeoutError
            ``solve`` (and the expansion of its solutions) ran longer than
            ``thetahat.limits.SYMBOLIC_TIME_BUDGET``.
        DimensionError
            Θ and g disagree on p.
        """
        if not isinstance(perturbation, SymbolicPerturbation):
            raise UpdateLawError("from_perturbation needs a SymbolicPerturbation (with expr, "
                                 "u, y, x, theta); for other perturbations pass theta_star.")
        n, m, r, p, k = perturbation.dims
        if parameter_set.dim != p:
            raise DimensionError(f"parameter_set has dimension {parameter_set.dim} but the "
                                 f"perturbation has p = {p} parameters.")
        require_theta_dependence(perturbation, parameter_set, owner="from_perturbation")
        u, y, x, th = (tuple(getattr(perturbation, a)) for a in ("u", "y", "x", "theta"))
        reps = {s: sp.Dummy(s.name, real=True) for s in (*u, *y, *x, *th)}
        phi = [sp.Dummy(f"phi{i}", real=True) for i in range(k)]
        expr = sp.Matrix(perturbation.expr)
        eqs = [sp.Eq(expr[i].xreplace(reps), phi[i]) for i in range(k)]
        unknowns = [reps[t] for t in th]
        try:
            sols = limits.run_with_time_budget(_sympy_solve, eqs, unknowns,
                                               what="SymPy's solve of φ = g(v, x, θ) for θ*")
        except (NotImplementedError, ValueError, TypeError) as exc:
            raise UpdateLawError(f"SymPy cannot solve φ = g(v, x, θ) for θ ({exc}); pass "
                                 f"theta_star explicitly.") from exc
        args = tuple([reps[s] for s in (*u, *y, *x)] + phi)
        branches, underdetermined = [], False
        for sol, expanded in sols:
            if expanded is None:
                underdetermined = True
                continue
            exprs = tuple(sol[t] for t in unknowns)
            if any(e.has(sp.zoo, sp.nan) for e in exprs):
                continue
            # SymPy's raw form can overflow where θ* is harmless (LuGre: it multiplies by
            # exp(ω²/ω0²) and divides by it again, inf·0 = NaN for |ω| > 0.27); the expanded
            # form cancels such factors. Both are checked below and the better one is kept.
            forms = []
            for form in dict.fromkeys((exprs, expanded)):
                try:
                    forms.append(cls(expr=form, arguments=args, sizes=(m + r, n, k)))
                except Exception:  # noqa: BLE001 - SymPy raises many types for unprintable forms
                    continue
            branches.append(forms)
        good = _branches_that_invert(perturbation, parameter_set, seed, branches)
        if not good and underdetermined:
            raise UpdateLawError("SymPy's solution of φ = g(v, x, θ) leaves some parameters "
                                 "free: one value of φ does not determine θ (e.g. p > k). Use "
                                 "GradientInversion with persistent excitation "
                                 "(Proposition 4).")
        if len(good) != 1:
            found = "no" if not good else f"{len(good)}"
            raise UpdateLawError(f"SymPy found {len(sols)} solution(s) of φ = g(v, x, θ) but "
                                 f"{found} branch(es) recover θ ∈ Θ at random points; the "
                                 f"inverse is not unique (or not available) — pass theta_star "
                                 f"explicitly, or use GradientInversion (Propositions 3–4).")
        return good[0]

    def __call__(self, v: ArrayLike, x: ArrayLike, phi: ArrayLike) -> FloatArray:
        """θ*(v, x, φ); shape (..., p).

        Parameters
        ----------
        v : array_like, shape (..., m + r)
        x : array_like, shape (..., n)
        phi : array_like, shape (..., k)

        Returns
        -------
        ndarray, shape (..., p)
        """
        v_ = np.asarray(v, dtype=np.float64)
        x_ = np.asarray(x, dtype=np.float64)
        ph = np.asarray(phi, dtype=np.float64)
        args = [*v_.T, *x_.T, *ph.T]      # one array per symbol (.T: the last axis first)
        with np.errstate(all="ignore"):
            vals = self.fn(*args)
        batch = v_.shape[:-1]
        out = None
        if batch == x_.shape[:-1] == ph.shape[:-1]:     # fast paths: no broadcasting needed
            if not batch:
                out = np.array(vals)
            elif all(type(val) is np.ndarray and val.shape == batch[::-1] for val in vals):
                out = np.stack(vals).T
            if out is not None and out.dtype != np.float64:
                out = None
        if out is None:
            out = _assemble(vals, np.broadcast_shapes(batch, x_.shape[:-1], ph.shape[:-1]))
        if not np.isfinite(out).all():
            out[~np.isfinite(out)] = np.nan
        return out

    def __eq__(self, other: object) -> bool:
        """Equal when the expressions, arguments and sizes are (the numerics follow from them)."""
        if not isinstance(other, ThetaStar):
            return NotImplemented
        return (self.expr, self.arguments, self.sizes) == (other.expr, other.arguments,
                                                           other.sizes)

    def __hash__(self) -> int:
        return hash((self.expr, self.arguments, self.sizes))

    def __repr__(self) -> str:
        body = ", ".join(str(e) for e in self.expr)
        return f"ThetaStar({body})"


def as_theta_star(theta_star: Any, perturbation: SymbolicPerturbation) -> ThetaStar | None:
    """θ* as a :class:`ThetaStar` when its SymPy form is known, else None.

    A ThetaStar is returned as is; a model file's θ* (an expression object whose
    ``sympy_form`` is (entries, arguments col(u, y), x, φ)) becomes the ThetaStar of that form;
    a plain Python callable has no SymPy form (None).

    Parameters
    ----------
    theta_star : ThetaStar, model-file θ* or callable
    perturbation : SymbolicPerturbation
        The g it inverts (its dimensions split the arguments).

    Returns
    -------
    ThetaStar or None

    Examples
    --------
    >>> from thetahat.modelfile import loads_model
    >>> spec = loads_model('''
    ... [system]
    ... A = [[0.0, 1.0], [-1.0, -0.5]]
    ... B = [[0.0], [1.0]]
    ... C = [[1.0, 0.0]]
    ... E = [[0.0], [1.0]]
    ... [perturbation]
    ... g = "(1 + y**2)*sinh(theta)"
    ... u = ["u"]
    ... y = ["y"]
    ... x = ["x1", "x2"]
    ... theta = ["theta"]
    ... [parameter_set]
    ... lower = [-0.5]
    ... upper = [0.5]
    ... [estimator]
    ... law = "algebraic"
    ... theta_star = "asinh(phi/(1 + y**2))"
    ... ''')
    >>> as_theta_star(spec.estimator.update_law.theta_star, spec.system.perturbation)
    ThetaStar(asinh(phi/(y**2 + 1)))
    """
    if isinstance(theta_star, ThetaStar):
        return theta_star
    form = getattr(theta_star, "sympy_form", None)
    if form is None:
        return None
    n, m, r, _, k = perturbation.dims
    expr, arguments = form
    return ThetaStar(expr=expr, arguments=arguments, sizes=(m + r, n, k))


def _sympy_solve(eqs: list[sp.Eq], unknowns: list[sp.Symbol]
                 ) -> list[tuple[dict[Any, Any], tuple[sp.Expr, ...] | None]]:
    """sp.solve and the expanded form of each complete solution (None for the others):
    module-level, so that all of the symbolic work runs in one time-budgeted worker."""
    out = []
    for sol in sp.solve(eqs, unknowns, dict=True, check=False, simplify=False):
        complete = set(unknowns) <= set(sol) and not any(
            sol[t].free_symbols & set(unknowns) for t in unknowns)
        out.append((sol, tuple(sp.expand(sol[t]) for t in unknowns) if complete else None))
    return out


def _assemble(vals: Sequence[Any], shape: tuple[int, ...]) -> FloatArray:
    """Stack the values of θ*'s entries to (*shape, p); complex values with a non-negligible
    imaginary part (a branch that is not real there) become NaN."""
    out = np.empty(shape + (len(vals),), dtype=np.result_type(*vals, np.float64))
    for j, val in enumerate(vals):
        out[..., j] = val
    if np.iscomplexobj(out):
        real = np.abs(out.imag) <= SOLVE_RTOL * (1.0 + np.abs(out.real))
        out = np.where(real, out.real, np.nan)
    return np.asarray(out, dtype=np.float64)


def _branches_that_invert(perturbation: Perturbation, parameter_set: ParameterSet, seed: int,
                          branches: list[list[ThetaStar]]) -> list[ThetaStar]:
    """Per branch, the form that recovers θ at the random points (branches with none: none)."""
    n, m, r, _, _ = perturbation.dims
    rng = np.random.default_rng(seed)
    theta_s = parameter_set.sample(rng, SOLVE_SAMPLES)
    v_s = rng.standard_normal((SOLVE_SAMPLES, m + r))
    x_s = rng.standard_normal((SOLVE_SAMPLES, n))
    phi_s = np.asarray(perturbation.g(v_s, x_s, theta_s), dtype=np.float64)
    good = []
    for forms in branches:
        best, best_ok = None, SOLVE_SAMPLES // 2 - 1
        for cand in forms:
            try:
                est = cand(v_s, x_s, phi_s)
            except Exception:  # noqa: BLE001 - a form numpy cannot evaluate is no inverse
                continue
            ok = np.all(np.isfinite(est), axis=-1)
            err = np.max(np.abs(est - theta_s), axis=-1)
            if (np.sum(ok) > best_ok and np.all(
                    err[ok] <= SOLVE_RTOL * (1 + np.max(np.abs(theta_s[ok]), axis=-1)))):
                best, best_ok = cand, int(np.sum(ok))
        if best is not None:
            good.append(best)
    return good


def _rebuild_theta_star(expr: tuple[Any, ...], arguments: tuple[Any, ...],
                        sizes: tuple[int, int, int]) -> ThetaStar:
    """Unpickle a :class:`ThetaStar` (see its ``__reduce__``)."""
    return ThetaStar(expr=expr, arguments=arguments, sizes=sizes)
