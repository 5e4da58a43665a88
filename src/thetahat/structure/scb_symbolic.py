"""The special coordinate basis (SCB) of a symbolic triple (C, A, B), computed exactly.

The numeric :func:`thetahat.structure.scb.scb` works on floating-point matrices. This module
builds the same decomposition, form (5) for SISO and form (6) for MIMO systems of Grip, Saberi
& Johansen, for SymPy matrices whose entries are expressions in symbolic parameters, the way
the paper's Sec. VIII prints the SCB of the DC motor with LuGre friction in terms of J, σ₀,
σ₁ and α₂.

Exact algebra decides every rank question *generically*: an expression counts as nonzero
unless it cancels to zero identically. The structure returned is therefore the one that holds
for almost all parameter values. It can change on the set where ``generic_condition``
vanishes (for the DC motor, σ₁ = 0 raises the relative degree from 2 to 3; see Sec. VII).
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Callable, Sequence

import sympy as sp

from .. import limits
from ..errors import DimensionError, NotLeftInvertibleError, UnsupportedError
from ..model.parse import parse_expression

__all__ = ["SymbolicSCBResult", "scb_symbolic"]

Matrix = sp.ImmutableMatrix


# ---------------------------------------------------------------------------------------------
# exact linear algebra with a generic zero test
# ---------------------------------------------------------------------------------------------

def _is_zero(e: Any) -> bool:
    """True iff ``e`` vanishes identically (cancel is canonical for rational functions)."""
    c = sp.cancel(sp.sympify(e))
    if c == 0:
        return True
    if c.is_number:
        return bool(c.equals(0))
    if c.is_rational_function():
        return False
    return bool(sp.simplify(c) == 0)


def _canon(M: sp.MatrixBase) -> sp.MutableDenseMatrix:
    """Entry-wise canonical form p/q (keeps intermediate expressions small)."""
    return sp.Matrix(M).applyfunc(sp.cancel)


def _rref(M: sp.MatrixBase) -> tuple[sp.MutableDenseMatrix, list[int]]:
    """Reduced row echelon form with generic pivots; the simplest nonzero entry is the pivot."""
    R = _canon(M)
    rows, cols = R.shape
    pivots: list[int] = []
    r = 0
    for c in range(cols):
        if r == rows:
            break
        cands = [i for i in range(r, rows) if not _is_zero(R[i, c])]
        if not cands:
            continue
        p = min(cands, key=lambda i: (not R[i, c].is_number, sp.count_ops(R[i, c])))
        R.row_swap(r, p)
        piv = R[r, c]
        R[r, :] = (R[r, :] / piv).applyfunc(sp.cancel)
        for i in range(rows):
            if i != r and not _is_zero(R[i, c]):
                R[i, :] = (R[i, :] - R[i, c] * R[r, :]).applyfunc(sp.cancel)
        pivots.append(c)
        r += 1
    return R, pivots


def _rank(M: sp.MatrixBase) -> int:
    return len(_rref(M)[1]) if M.rows and M.cols else 0


def _nullspace(M: sp.MatrixBase) -> sp.MutableDenseMatrix:
    """Basis of ker M as columns (one free variable set to 1 per vector)."""
    n = M.cols
    if M.rows == 0:
        return sp.eye(n)
    R, pivots = _rref(M)
    free = [c for c in range(n) if c not in pivots]
    N = sp.zeros(n, len(free))
    for j, f in enumerate(free):
        N[f, j] = 1
        for i, p in enumerate(pivots):
            N[p, j] = -R[i, f]
    return N


def _colspace(M: sp.MatrixBase) -> sp.MutableDenseMatrix:
    """Basis of im M: the pivot columns of M itself."""
    if M.cols == 0 or M.rows == 0:
        return sp.zeros(M.rows, 0)
    _, pivots = _rref(M)
    return sp.Matrix.hstack(sp.zeros(M.rows, 0), *[M[:, c] for c in pivots])


def _left_null(M: sp.MatrixBase) -> sp.MutableDenseMatrix:
    """Basis of the rows w with w M = 0, as the rows of the returned matrix."""
    return _nullspace(M.T).T


def _extend(base: sp.MatrixBase, cand: sp.MatrixBase) -> sp.MutableDenseMatrix:
    """Rows of ``cand`` that extend the (independent) rows of ``base`` to a larger basis."""
    if cand.rows == 0:
        return sp.zeros(0, cand.cols)
    _, pivots = _rref(sp.Matrix.vstack(base, cand).T)
    keep = [p - base.rows for p in pivots if p >= base.rows]
    return sp.Matrix.vstack(sp.zeros(0, cand.cols), *[cand[i, :] for i in keep])


def _solve_left(G: sp.MatrixBase, h: sp.MatrixBase) -> sp.MutableDenseMatrix:
    """Solve x G = h exactly; raise UnsupportedError when inconsistent or not unique."""
    p = G.rows
    R, pivots = _rref(sp.Matrix.hstack(G.T, h.T))
    if pivots != list(range(p)):
        raise UnsupportedError(
            "scb_symbolic: a linear system for the SCB has no unique generic solution; the "
            "structure of this triple is not generic. Substitute numbers and use the numeric "
            "scb instead.")
    return R[:p, p:].T


def _inv(M: sp.MatrixBase, what: str) -> sp.MutableDenseMatrix:
    n = M.rows
    R, pivots = _rref(sp.Matrix.hstack(M, sp.eye(n)))
    if pivots[:n] != list(range(n)):
        raise UnsupportedError(
            f"scb_symbolic: the {what} is singular for generic parameter values, so this triple "
            f"does not have the generic structure this routine builds. Substitute numbers and "
            f"use the numeric scb instead.")
    return R[:, n:]


def _generic_rank(M: sp.MatrixBase, extra: Sequence[sp.Symbol] = ()) -> int:
    """Rank at a pseudo-random rational point (generic rank with probability one)."""
    syms = sorted(M.free_symbols | set(extra), key=str)
    vals = {s: sp.Rational(7 + 13 * i, 11 + 3 * i) for i, s in enumerate(syms)}
    return int(M.subs(vals).rank())


# ---------------------------------------------------------------------------------------------
# the result
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True, repr=False)
class SymbolicSCBResult:
    """The special coordinate basis of a symbolic triple, forms (5) and (6).

    x = Γs χ, y = Γo γ, u = Γi δ with χ = col(χ_a, χ_b, χ_q1, …, χ_qk) and
    γ = col(γ_q1, …, γ_qk, γ_b). Every matrix is a :class:`sympy.ImmutableMatrix`.

    Attributes
    ----------
    n_a, n_b : int
        Dimensions of the zero dynamics χ_a and of the χ_b subsystem.
    chain_lengths : tuple of int
        n_qj, the lengths of the integrator chains, in χ order (ascending).
    invariant_zeros : list of sympy.Expr or None
        The roots of det(sI − A_a), with multiplicity; ``None`` when SymPy cannot give all of
        them in closed form (then use ``zero_polynomial``).
    zero_polynomial : sympy.Poly
        det(sI − A_a), monic in the variable ``s`` (``zero_polynomial.gen``).
    generic_condition : sympy.Expr
        The structure is valid where this expression is nonzero: C A^{n_q−1} B for SISO
        systems, the determinant of the decoupling matrix (rows T_j,last B) for MIMO ones,
        times res(det(sI − A_a), det(sI − A_b)) when the Sylvester step was used (the
        spectra of A_a and A_b must be disjoint). Denominators of individual entries may
        vanish at further parameter values; there the basis, not the structure, breaks down.
    state_transform, output_transform, input_transform : sympy.ImmutableMatrix
        Γs (n × n), Γo (r × r), Γi (k × k).
    A_tilde, B_tilde, C_tilde : sympy.ImmutableMatrix
        Γs⁻¹ A Γs, Γs⁻¹ B Γi, Γo⁻¹ C Γs.
    A_a, L_aq, L_ab : sympy.ImmutableMatrix
        (n_a × n_a), (n_a × k), (n_a × (r − k)): χ̇_a = A_a χ_a + L_aq γ_q + L_ab γ_b.
    A_b, L_bq, C_b : sympy.ImmutableMatrix
        (n_b × n_b), (n_b × k), ((r − k) × n_b): χ̇_b = A_b χ_b + L_bq γ_q, γ_b = C_b χ_b.
    L_qq : sympy.ImmutableMatrix
        (n_q × k) output injection from the chain tops into the chain rows; its last-row
        entries are zero (those couplings are part of ``D_q``).
    D_a, D_b, D_q : sympy.ImmutableMatrix
        (k × n_a), (k × n_b), (k × n_q): χ̇_qj,last = D_aj χ_a + D_bj χ_b + D_qj χ_q + δ_j.
    """

    n_a: int
    n_b: int
    chain_lengths: tuple[int, ...]
    invariant_zeros: list[sp.Expr] | None
    zero_polynomial: sp.Poly
    generic_condition: sp.Expr
    state_transform: Matrix
    output_transform: Matrix
    input_transform: Matrix
    A_tilde: Matrix
    B_tilde: Matrix
    C_tilde: Matrix
    A_a: Matrix
    L_aq: Matrix
    L_ab: Matrix
    A_b: Matrix
    L_bq: Matrix
    C_b: Matrix
    L_qq: Matrix
    D_a: Matrix
    D_b: Matrix
    D_q: Matrix

    @property
    def n_q(self) -> int:
        """Number of chain states, Σ n_qj (the infinite-zero structure)."""
        return sum(self.chain_lengths)

    @property
    def k(self) -> int:
        """Number of chains (= inputs)."""
        return len(self.chain_lengths)

    @property
    def r_b(self) -> int:
        """Number of γ_b outputs, r − k."""
        return self.C_b.rows

    def chain_slices(self) -> tuple[slice, ...]:
        """Slices of χ holding each chain χ_qj."""
        ends = [self.n_a + self.n_b + sum(self.chain_lengths[: j + 1]) for j in range(self.k)]
        return tuple(slice(end - L, end) for end, L in zip(ends, self.chain_lengths))

    def __repr__(self) -> str:
        zeros = (self.invariant_zeros if self.invariant_zeros is not None
                 else self.zero_polynomial.as_expr())
        return (f"SymbolicSCBResult(n_a={self.n_a}, n_b={self.n_b}, "
                f"chain_lengths={self.chain_lengths}, invariant_zeros={zeros}, "
                f"generic_condition={self.generic_condition} != 0)")

    def pretty(self) -> str:
        """Multi-line, human-readable rendering of the structure and its blocks."""
        lines = [f"SCB (valid where {self.generic_condition} != 0): n_a = {self.n_a}, "
                 f"n_b = {self.n_b}, chains = {self.chain_lengths}",
                 f"invariant zeros: {self.invariant_zeros}  "
                 f"(roots of {self.zero_polynomial.as_expr()})"]
        for name in ("A_a", "L_aq", "L_ab", "A_b", "L_bq", "C_b", "L_qq", "D_a", "D_b",
                     "D_q", "state_transform", "output_transform", "input_transform"):
            M = getattr(self, name)
            if M.rows and M.cols:
                lines.append(f"{name} =")
                lines.append(sp.pretty(M, use_unicode=True))
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# construction
# ---------------------------------------------------------------------------------------------

def _rows_of(name: str, M: Any) -> list[list[Any]]:
    """Nested lists of the entries of M (a SymPy matrix, an array, or nested sequences)."""
    if isinstance(M, sp.MatrixBase):
        return M.tolist()
    if isinstance(M, (str, bytes)) or not hasattr(M, "__iter__"):
        raise DimensionError(f"{name} must be a 2-D SymPy matrix or nested lists of entries; "
                             f"got {type(M).__name__}.")
    rows = list(M.tolist() if hasattr(M, "tolist") else M)
    if rows and all(isinstance(r, (str, bytes)) or not hasattr(r, "__iter__") for r in rows):
        return [[e] for e in rows]                       # a flat list is a column
    out = []
    for r in rows:
        if isinstance(r, (str, bytes)) or not hasattr(r, "__iter__"):
            raise DimensionError(f"{name} mixes rows and single entries; give a list of rows.")
        out.append(list(r))
    return out


def _as_sym_matrices(**mats: Any) -> dict[str, sp.MutableDenseMatrix]:
    """SymPy matrices of A, B, C; string entries go through the safe parser, never sympify."""
    rows = {name: _rows_of(name, M) for name, M in mats.items()}
    for name, R in rows.items():
        if len(R) > limits.MAX_SYMBOLIC_DIM or any(len(r) > limits.MAX_SYMBOLIC_DIM
                                                   for r in R):
            raise DimensionError(
                f"{name} has more than {limits.MAX_SYMBOLIC_DIM} rows or columns; the exact "
                f"SCB is limited to that size (thetahat.limits.MAX_SYMBOLIC_DIM). Substitute "
                f"numbers and use the numeric scb.")
    known: dict[str, sp.Symbol] = {}
    for R in rows.values():
        for r in R:
            for e in r:
                if isinstance(e, sp.Basic):
                    known.update({str(s): s for s in e.free_symbols})

    def symbol(name: str) -> sp.Expr:
        return known.setdefault(name, sp.Symbol(name))

    out = {}
    for name, R in rows.items():
        conv = []
        for i, r in enumerate(R):
            row = []
            for j, e in enumerate(r):
                if isinstance(e, str):
                    e = parse_expression(e, {}, what=f"{name}[{i}][{j}]", new_symbol=symbol)
                elif isinstance(e, bool) or not isinstance(e, (sp.Basic, int, float,
                                                               complex, Fraction)) and \
                        not (hasattr(e, "dtype") and getattr(e.dtype, "kind", "") in "iuf"):
                    raise DimensionError(f"{name}[{i}][{j}] must be a number, a SymPy "
                                         f"expression or a formula string; got "
                                         f"{type(e).__name__}.")
                row.append(sp.sympify(e, strict=True))
            conv.append(row)
        widths = {len(r) for r in conv}
        if len(widths) > 1:
            raise DimensionError(f"{name}: rows have different lengths {sorted(widths)}.")
        try:
            out[name] = sp.Matrix(conv) if conv else sp.zeros(0, 0)
        except (TypeError, ValueError) as exc:
            raise DimensionError(f"{name} must be a 2-D matrix; {exc}") from exc
    return out


def _validate(A: Any, B: Any, C: Any) -> tuple[sp.Matrix, sp.Matrix, sp.Matrix]:
    mats = _as_sym_matrices(A=A, B=B, C=C)
    A_, B_, C_ = mats["A"], mats["B"], mats["C"]
    n = A_.rows
    if A_.cols != n or n == 0:
        raise DimensionError(f"A must be square and nonempty; got shape {A_.shape}.")
    if B_.rows != n or B_.cols == 0:
        raise DimensionError(f"B must have shape ({n}, k) with k >= 1; got {B_.shape}.")
    if C_.cols != n or C_.rows == 0:
        raise DimensionError(f"C must have shape (r, {n}) with r >= 1; got {C_.shape}.")
    if _rank(C_) < C_.rows:
        raise DimensionError(f"C (shape {C_.shape}) must have full row rank {C_.rows} for "
                             f"generic parameter values; remove the redundant outputs.")
    return A_, B_, C_


def _siso_rows(A: sp.Matrix, B: sp.Matrix, C: sp.Matrix) -> sp.Matrix:
    """Chain rows C A^{i−1}, i = 1..n_q, where C A^{n_q−1} B is the first Markov parameter ≢ 0."""
    n = A.rows
    row = C
    rows: list[sp.Matrix] = []
    for _ in range(n):
        rows.append(row)
        lead = sp.cancel((row * B)[0, 0])
        if not _is_zero(lead):
            return sp.Matrix.vstack(*rows)
        row = _canon(row * A)
    V = _nullspace(C)  # C (sI − A)⁻¹ B ≡ 0: ker C holds the controllable subspace
    dim_int = _rank(B) + V.cols - _rank(sp.Matrix.hstack(V, B)) if V.cols else 0
    raise NotLeftInvertibleError(
        "scb_symbolic: the SISO triple (C, A, B) is not left-invertible: every Markov "
        "parameter C A^i B (i < n) is identically zero, so the transfer function vanishes and "
        "there is no relative degree. Check how the input and output enter the model.",
        rank_B=_rank(B), normal_rank=_rosenbrock_rank(A, B, C), dim_intersection=dim_int)


def _rosenbrock_rank(A: sp.Matrix, B: sp.Matrix, C: sp.Matrix) -> int:
    s = sp.Dummy("s")
    n, k, r = A.rows, B.cols, C.rows
    P = sp.Matrix.vstack(sp.Matrix.hstack(s * sp.eye(n) - A, -B),
                         sp.Matrix.hstack(C, sp.zeros(r, k)))
    return _generic_rank(P, (s,))


def _subspace_sequence(A: sp.Matrix, B: sp.Matrix, C: sp.Matrix) -> list[sp.Matrix]:
    """Bases of S_0 = 0, S_1 = im B, S_{i+1} = A (S_i ∩ ker C) + im B, up to S*."""
    S = _colspace(B)
    seq = [sp.zeros(A.rows, 0), S]
    while True:
        Z = _canon(S * _nullspace(C * S))
        S_next = _colspace(_canon(sp.Matrix.hstack(A * Z, B)))
        if S_next.cols == S.cols:
            return seq
        S = S_next
        seq.append(S)


def _v_star(A: sp.Matrix, B: sp.Matrix, C: sp.Matrix) -> sp.Matrix:
    """Basis of V*: V_0 = ker C, V_{i+1} = ker C ∩ A⁻¹(V_i + im B)."""
    V = _nullspace(C)
    while True:
        N = _left_null(sp.Matrix.hstack(V, B))
        V_next = _nullspace(_canon(sp.Matrix.vstack(C, N * A)))
        if V_next.cols == V.cols:
            return V_next
        V = V_next


def _mimo_rows(A: sp.Matrix, B: sp.Matrix, C: sp.Matrix
               ) -> tuple[sp.Matrix, sp.Matrix, sp.Matrix, sp.Matrix, tuple[int, ...]]:
    """Rows T_q (chains), T_b, T_a0 and the output rows W = Γo⁻¹, from S_i, V* (exact)."""
    n, k, r = A.rows, B.cols, C.rows
    rank_B = _rank(B)
    S_seq = _subspace_sequence(A, B, C)
    S_star = S_seq[-1]
    V_star = _v_star(A, B, C)
    n_a, n_q = V_star.cols, S_star.cols
    overlap = n_a + n_q - _rank(sp.Matrix.hstack(V_star, S_star))
    if rank_B < k or overlap > 0:
        dim_int = n_a + rank_B - _rank(sp.Matrix.hstack(V_star, B))
        why = (f"B has rank {rank_B} < k = {k}" if rank_B < k else
               f"V* ∩ S* has dimension {overlap} > 0 (an input direction can be steered "
               f"without ever reaching the output)")
        raise NotLeftInvertibleError(
            f"scb_symbolic: the triple (C, A, B) is not left-invertible for generic parameter "
            f"values: {why}. The observer needs Assumption 1: each perturbation component must "
            f"be visible in y.", rank_B=rank_B, normal_rank=_rosenbrock_rank(A, B, C),
            dim_intersection=dim_int)
    dims = [S.cols for S in S_seq]
    ge = [dims[i] - dims[i - 1] for i in range(1, len(dims))] + [0]  # chains of length >= i
    count = {L: ge[L - 1] - ge[L] for L in range(1, len(dims))}
    # output directions: γ_b rows annihilate S*, chain tops of length L annihilate S_{L−1}
    W_b = _left_null(_canon(C * S_star))
    collected, tops = W_b, []
    for L in range(len(dims) - 1, 0, -1):
        new = _extend(collected, _left_null(_canon(C * S_seq[L - 1])))
        if new.rows != count[L]:
            raise UnsupportedError(
                f"scb_symbolic: found {new.rows} output directions for chains of length {L}, "
                f"expected {count[L]}; the structure is not generic.")
        tops += [(L, new[i, :]) for i in range(new.rows)]
        collected = sp.Matrix.vstack(collected, new)
    tops.sort(key=lambda t: t[0])
    lengths = tuple(L for L, _ in tops)
    top_rows = [_canon(w * C) for _, w in tops]
    chain_rows: list[sp.Matrix] = []
    for (L, _), t in zip(tops, top_rows):
        row = t
        chain_rows.append(row)
        for i in range(1, L):
            row = _canon(row * A)
            m = L - i - 1                       # the next row must annihilate S_m
            short = [tr for (Lj, _), tr in zip(tops, top_rows) if Lj <= m]
            if m >= 1 and short:
                Ts = sp.Matrix.vstack(*short)
                ell = _solve_left(_canon(Ts * S_seq[m]), _canon(row * S_seq[m]))
                row = _canon(row - ell * Ts)
            chain_rows.append(row)
    T_q = sp.Matrix.vstack(*chain_rows)
    W = sp.Matrix.vstack(*[w for _, w in tops], W_b)
    n_b = n - n_a - n_q
    T_b = sp.zeros(0, n)
    if n_b:
        T_b = _extend(sp.zeros(0, n), sp.Matrix.vstack(
            _canon(W_b * C), _left_null(sp.Matrix.hstack(V_star, S_star))))
    T_a0 = _extend(T_b, _left_null(S_star)) if n_a else sp.zeros(0, n)
    if T_b.rows != n_b or T_a0.rows != n_a or r - k != W_b.rows:
        raise UnsupportedError("scb_symbolic: inconsistent subspace dimensions; the "
                                  "structure of this triple is not generic.")
    return T_q, T_b, T_a0, W, lengths


def _remove_ab_coupling(At: sp.Matrix, n_a: int, n_b: int, C_b: sp.Matrix
                        ) -> tuple[sp.Matrix | None, sp.Matrix, sp.Expr]:
    """Sylvester step: X with A_a X − X A_b = −A_ab, or None if A_ab = L_ab C_b already.

    Also returns the condition for the step, res(det(sI − A_a), det(sI − A_b)) (1 if unused).
    """
    a, b = slice(0, n_a), slice(n_a, n_a + n_b)
    A_a, A_ab, A_b = At[a, a], At[a, b], At[b, b]
    try:
        return None, _solve_left(C_b, A_ab), sp.Integer(1)
    except UnsupportedError:
        pass
    K = sp.zeros(n_a * n_b, n_a * n_b)
    for j in range(n_b):
        for i in range(n_a):
            for i2 in range(n_a):
                K[i + j * n_a, i2 + j * n_a] += A_a[i, i2]
            for j2 in range(n_b):
                K[i + j * n_a, i + j2 * n_a] -= A_b[j2, j]
    rhs = sp.Matrix([-A_ab[i, j] for j in range(n_b) for i in range(n_a)])
    R, piv = _rref(sp.Matrix.hstack(K, rhs))
    if piv != list(range(n_a * n_b)):
        raise UnsupportedError(
            "scb_symbolic: A_a and A_b share eigenvalues for generic parameter values, so the "
            "Sylvester step that removes the a–b coupling not passing through C_b has no unique "
            "solution; this MIMO case (n_a > 0, n_b > 0) is not supported symbolically. "
            "Substitute numbers and use the numeric scb.")
    X = sp.Matrix(n_a, n_b, lambda i, j: R[i + j * n_a, -1])
    lam = sp.Dummy("lambda")
    disjoint = sp.resultant(sp.Poly(A_a.charpoly(lam).all_coeffs(), lam),
                            sp.Poly(A_b.charpoly(lam).all_coeffs(), lam))
    return X, sp.zeros(n_a, C_b.rows), sp.cancel(disjoint)


def _tidy(e: sp.Expr) -> sp.Expr:
    c = sp.cancel(e)
    return sp.factor(c) if c.is_rational_function() else sp.simplify(c)


def _zeros_of(A_a: sp.Matrix, s: sp.Symbol, tidy: Callable[[sp.Expr], sp.Expr]
              ) -> tuple[sp.Poly, list[sp.Expr] | None]:
    coeffs = A_a.charpoly(s).all_coeffs() if A_a.rows else [sp.Integer(1)]
    poly = sp.Poly([tidy(c) for c in coeffs], s)
    found = sp.roots(poly)
    if sum(found.values()) != A_a.rows:
        return poly, None
    zeros = [tidy(z) for z, mult in found.items() for _ in range(mult)]
    return poly, zeros


def scb_symbolic(A: Any, B: Any, C: Any, *, simplify: bool = True) -> SymbolicSCBResult:
    """Special coordinate basis of a symbolic strictly proper triple, forms (5) and (6).

    Parameters
    ----------
    A : sympy.Matrix, shape (n, n)
    B : sympy.Matrix, shape (n, k)
        Input matrix (for the paper's use: E augmented by integrators, eq. (4)).
    C : sympy.Matrix, shape (r, n)
        Output matrix, full row rank, r >= k.
    simplify : bool, default True
        Factor every entry of the result. With ``False`` entries are left as cancelled
        (expanded) rational functions, which is faster for large expressions.

    Returns
    -------
    SymbolicSCBResult
        Transforms Γs, Γo, Γi with x = Γs χ, y = Γo γ, u = Γi δ, the transformed triple and
        the blocks of (6).

    Raises
    ------
    DimensionError
        Non-matching shapes, or C without full row rank.
    NotLeftInvertibleError
        The triple is not left-invertible for generic parameter values.
    UnsupportedError
        A MIMO case outside the supported class (see Notes).
    ModelFileError, InputLimitError
        A string entry is not a formula in the safe syntax of
        :func:`~thetahat.model.parse.parse_expression` (strings are parsed, never evaluated;
        undeclared names become symbols), or exceeds a limit of :mod:`thetahat.limits`.
    SymbolicTimeoutError
        The exact algebra took longer than ``thetahat.limits.SYMBOLIC_TIME_BUDGET``.

    Notes
    -----
    The decomposition is the *generic* one: an expression is treated as nonzero unless it
    cancels to zero identically, so the structure holds for all parameter values except a
    set of measure zero, where ``generic_condition`` (or an intermediate rank) vanishes.

    *SISO.* The relative degree n_q is the smallest i with C A^{i−1} B ≢ 0, and
    ``generic_condition`` = C A^{n_q−1} B. The chain rows are C A^{i−1}, Γi = 1/(C A^{n_q−1}B),
    Γo = 1 (the chain top is y itself, no rescaling of γ), and the zero-dynamics rows T_a span
    the left null space of [B, AB, …, A^{n_q−1} B]; then T_a A = A_a T_a + L_aq C, eq. (5).

    *MIMO.* S_1 = im B, S_{i+1} = A(S_i ∩ ker C) + im B give the chain counts; V* gives n_a.
    Chain tops of length L are outputs annihilating C S_{L−1}; chain rows follow
    T_{j,i+1} = T_{j,i} A − ℓᵀ γ_q with ℓ chosen so that T_{j,i+1} annihilates S_{n_qj−i−1};
    b-rows annihilate V* + S*; a-rows annihilate S* and are corrected by the Sylvester
    equation A_a X − X A_b = −A_ab when the a-rows see χ_b other than through C_b. Supported:
    square invertible systems (n_b = 0), and n_b > 0 whenever either no correction is needed
    or eig A_a and eig A_b are generically disjoint. Chains are ordered by ascending length.

    The χ_a basis, and with it L_aq, L_ab and D_a, is a free choice of the SCB; A_a up to
    similarity, D_q, and products such as L_aq D_a are invariant.

    References
    ----------
    Grip, Saberi & Johansen, Sec. III (forms (5), (6)) and Sec. VIII; Sannuti & Saberi (1987).

    Examples
    --------
    The extended error system of the DC motor with LuGre friction (Sec. VIII):

    >>> import sympy as sp
    >>> from thetahat.structure.scb_symbolic import scb_symbolic
    >>> J, s0, s1, a2 = sp.symbols("J sigma0 sigma1 alpha2", positive=True)
    >>> A = sp.Matrix([[-(a2 + s1) / J, -s0 / J, s1 / J], [1, 0, -1], [0, 0, 0]])
    >>> res = scb_symbolic(A, sp.Matrix([0, 0, 1]), sp.Matrix([[1, 0, 0]]))
    >>> res.n_a, res.chain_lengths, res.A_a[0, 0], res.generic_condition
    (1, (2,), -sigma0/sigma1, sigma1/J)
    >>> scb_symbolic(A.subs(s1, 0), sp.Matrix([0, 0, 1]), sp.Matrix([[1, 0, 0]])).D_q
    Matrix([[0, -sigma0/J, -alpha2/J]])
    """
    A_, B_, C_ = _validate(A, B, C)
    return limits.run_with_time_budget(_build, A_, B_, C_, simplify,
                                       what="scb_symbolic (exact SCB algebra)")


def _build(A_: sp.Matrix, B_: sp.Matrix, C_: sp.Matrix, simplify: bool) -> SymbolicSCBResult:
    n, k, r = A_.rows, B_.cols, C_.rows
    if k == 1 and r == 1:
        T_q, W = _siso_rows(A_, B_, C_), sp.Matrix([[1]])
        n_q = T_q.rows
        T_a = _left_null(_canon(sp.Matrix.hstack(*[A_ ** i * B_ for i in range(n_q)])))
        T_b, lengths = sp.zeros(0, n), (n_q,)
    else:
        T_q, T_b, T_a, W, lengths = _mimo_rows(A_, B_, C_)
    n_a, n_b, n_q = T_a.rows, T_b.rows, T_q.rows
    lasts = [sum(lengths[: j + 1]) - 1 for j in range(k)]
    tops = [sum(lengths[:j]) for j in range(k)]
    M = _canon(T_q[lasts, :] * B_)
    lead = M[0, 0] if k == 1 else sp.cancel(M.det())
    Gi = _inv(M, "decoupling matrix (rows T_j,last B)")
    T = sp.Matrix.vstack(T_a, T_b, T_q)
    Gs = _inv(T, "state transform Γs⁻¹")
    At = _canon(T * A_ * Gs)
    Wi = _inv(W, "output transform Γo⁻¹")
    a, b = slice(0, n_a), slice(n_a, n_a + n_b)
    C_b = _canon(W[k:, :] * C_ * Gs[:, b])
    L_ab = sp.zeros(n_a, r - k)
    if n_a and n_b:
        X, L_ab, disjoint = _remove_ab_coupling(At, n_a, n_b, C_b)
        lead = sp.cancel(lead * disjoint)
        if X is not None:
            T[a, :] = _canon(T[a, :] - X * T_b)
            Gs[:, b] = _canon(Gs[:, b] + Gs[:, a] * X)
            At = _canon(T * A_ * Gs)
    tidy = _tidy if simplify else sp.cancel

    def fin(Mx: sp.MatrixBase) -> Matrix:
        return Matrix(sp.Matrix(Mx).applyfunc(tidy))

    At_f, Ct_f = fin(At), fin(W * C_ * Gs)
    q = slice(n_a + n_b, n)
    L_qq = sp.Matrix(At_f[q, [n_a + n_b + t for t in tops]])
    for j in lasts:
        L_qq[j, :] = sp.zeros(1, k)
    s = sp.Symbol("s")
    if s in (A_.free_symbols | B_.free_symbols | C_.free_symbols):
        s = sp.Dummy("s")
    poly, zeros = _zeros_of(At_f[a, a], s, tidy)
    lastq = [n_a + n_b + j for j in lasts]
    return SymbolicSCBResult(
        n_a=n_a, n_b=n_b, chain_lengths=tuple(lengths), invariant_zeros=zeros,
        zero_polynomial=poly, generic_condition=tidy(lead),
        state_transform=fin(Gs), output_transform=fin(Wi), input_transform=fin(Gi),
        A_tilde=At_f, B_tilde=fin(T * B_ * Gi), C_tilde=Ct_f,
        A_a=Matrix(At_f[a, a]), L_aq=Matrix(At_f[a, [n_a + n_b + t for t in tops]]),
        L_ab=fin(L_ab), A_b=Matrix(At_f[b, b]),
        L_bq=Matrix(At_f[b, [n_a + n_b + t for t in tops]]), C_b=Matrix(Ct_f[k:, b]),
        L_qq=Matrix(L_qq), D_a=Matrix(At_f[lastq, a]), D_b=Matrix(At_f[lastq, b]),
        D_q=Matrix(At_f[lastq, q]))
