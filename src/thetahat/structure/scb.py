"""The special coordinate basis (SCB) of a strictly proper, left-invertible triple (Sec. III).

x = Γs χ, y = Γo γ, u = Γi δ take ẋ = A x + B u, y = C x to the form (5)/(6) of the paper:

    χ̇_a  = A_a χ_a + L_aq γ_q + L_ab γ_b                                  (6a)
    χ̇_b  = A_b χ_b + L_bq γ_q                                              (6b)
    χ̇_qj = A_qj χ_qj + L_qjq γ_q + B_qj (δ_j + D_aj χ_a + D_bj χ_b + D_qj χ_q) (6c)
    γ_b  = C_b χ_b,  γ_qj = C_qj χ_qj                                       (6d)

with χ = col(χ_a, χ_b, χ_q1, …, χ_qk), γ = col(γ_q1, …, γ_qk, γ_b), A_qj a shift, B_qj the
last unit vector and C_qj the first. Output injection L_qjq enters only the non-last rows of a
chain (in SISO there is none: (5)); output terms of a last row belong to D_qj.

Construction (see ``shared/notes/scb.md``): orthonormal bases of V* and of the nested S_i
(``subspaces.py``) give n_a, n_q and the chain lengths before any chain is built. The rows of
Γs⁻¹ are then built directly: chain tops are output directions chosen by SVD (a chain of
length L has its top in the outputs that annihilate S_{L−1} but not S_L), each next chain row
is the previous row times A minus the output injection that makes it annihilate the right S_i;
the b-rows span the annihilator of V* + S*; the a-rows complete the annihilator of S* and are
decoupled from the b-rows by a Sylvester equation. The result is checked (residual of the
pattern, reproduction of (A, B, C)) and reported.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from .._validate import as_triple
from ..errors import (DimensionError, IllConditionedError, IllConditionedWarning,
                      NotLeftInvertibleError)
from . import subspaces as sub
from .zeros import normal_rank, unstable_zeros

FloatArray = NDArray[np.float64]

#: Default rank tolerance on data normalised to unit norm. Far below any structural entry
#: of well-posed problems (the DC motor's smallest, σ1/(J‖A‖), is 2e-3) and far above
#: round-off (n·eps ≈ 1e-14 for n = 50).
DEFAULT_TOL = 1e-10
#: cond(Γs) above which a warning is issued (derivative coordinates are ill-conditioned by
#: nature; beyond this a design on a simplified system, Sec. VII, is usually better).
COND_WARN = 1e8
#: Pattern residual (relative) above which the construction is reported as failed.
RESIDUAL_FAIL = 1e-6


@dataclass(frozen=True, slots=True, repr=False)
class SCBResult:
    """The SCB of a triple (C, A, B): transforms, structure and the blocks of (6).

    Attributes
    ----------
    n_a, n_b : int
        Dimensions of the zero dynamics χ_a and of the χ_b block.
    chain_lengths : tuple of int
        n_q1, …, n_qk, in the order of the chains in χ (ascending length).
    invariant_zeros : ndarray of complex, shape (n_a,)
        eig(A_a), the invariant zeros of the triple.
    minimum_phase : bool
        All zeros in the open left half-plane (scaled tolerance, see ``unstable_zeros``).
    state_transform, output_transform, input_transform : ndarray
        Γs (n, n), Γo (r, r), Γi (k, k) with x = Γs χ, y = Γo γ, u = Γi δ.
    A_tilde, B_tilde, C_tilde : ndarray
        The transformed triple with the exact pattern (6) (entries the pattern fixes are set).
    A_a, L_aq, L_ab, A_b, L_bq, C_b, L_qq, D_a, D_b, D_q : ndarray
        The blocks of (6). ``L_qq`` (n_q, k) is the injection from the chain tops into the
        chain rows (zero in last rows); ``D_a`` (k, n_a), ``D_b`` (k, n_b), ``D_q`` (k, n_q)
        are the last rows of the chains.
    condition : float
        cond(Γs) (2-norm).
    residual : float
        Largest relative deviation of Γs⁻¹AΓs, Γs⁻¹BΓi, Γo⁻¹CΓs from the pattern before clean-up.
    tol : float
        The rank tolerance used (on normalised data).
    """

    n_a: int
    n_b: int
    chain_lengths: tuple[int, ...]
    invariant_zeros: NDArray[np.complex128]
    minimum_phase: bool
    state_transform: FloatArray
    output_transform: FloatArray
    input_transform: FloatArray
    A_tilde: FloatArray
    B_tilde: FloatArray
    C_tilde: FloatArray
    A_a: FloatArray
    L_aq: FloatArray
    L_ab: FloatArray
    A_b: FloatArray
    L_bq: FloatArray
    C_b: FloatArray
    L_qq: FloatArray
    D_a: FloatArray
    D_b: FloatArray
    D_q: FloatArray
    condition: float
    residual: float
    tol: float = field(default=DEFAULT_TOL)

    @property
    def n_q(self) -> int:
        """Number of chain states, Σ n_qj (the infinite zeros)."""
        return int(sum(self.chain_lengths))

    @property
    def k(self) -> int:
        """Number of chains (= inputs)."""
        return len(self.chain_lengths)

    @property
    def r_b(self) -> int:
        """Number of γ_b outputs, r − k."""
        return self.C_b.shape[0]

    def chain_slices(self) -> tuple[slice, ...]:
        """Slices of χ holding each chain χ_qj."""
        start = self.n_a + self.n_b
        out = []
        for L in self.chain_lengths:
            out.append(slice(start, start + L))
            start += L
        return tuple(out)

    def __repr__(self) -> str:
        z = ", ".join(f"{complex(v):.6g}" for v in self.invariant_zeros) or "none"
        return (f"SCBResult(n_a={self.n_a}, n_b={self.n_b}, chain_lengths={self.chain_lengths}, "
                f"zeros=[{z}], minimum_phase={self.minimum_phase}, "
                f"condition={self.condition:.3g}, residual={self.residual:.1e})")


def _normalised(M: FloatArray) -> FloatArray:
    nrm = np.linalg.norm(M, 2) if M.size else 0.0
    return M / nrm if nrm > 0 else M


#: Tolerances tried (in this order) to suggest one that works when the SCB of a left-invertible
#: triple fails at the requested tolerance.
SUGGEST_TOLS = (1e-12, 1e-14, 1e-8, 1e-6)


def _suggest_tol(A: FloatArray, B: FloatArray, C: FloatArray, tol: float) -> float | None:
    """The first of ``SUGGEST_TOLS`` (other than ``tol``) at which the SCB succeeds."""
    for cand in SUGGEST_TOLS:
        if cand == tol:
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                _scb(A, B, C, cand, suggest=False)
        except (IllConditionedError, NotLeftInvertibleError, DimensionError):
            continue
        return cand
    return None


def _ill_conditioned(A, B, C, tol: float, condition: float, what: str,
                     suggest: bool) -> IllConditionedError:
    """The error for a left-invertible triple whose SCB fails numerically at ``tol``."""
    cand = _suggest_tol(A, B, C, tol) if suggest else None
    fix = (f"scb(..., tol={cand:g}) succeeds for this triple" if cand is not None else
           f"no tolerance among {list(SUGGEST_TOLS)} works; rescale the states, or design "
           "on a simplified system (Sec. VII)")
    return IllConditionedError(
        f"the triple (C, A, B) is left-invertible (the Rosenbrock matrix has full normal rank, "
        f"the test of is_left_invertible), but too ill-conditioned to put in SCB form at "
        f"tol={tol:g}: {what}"
        + (f" (condition estimate {condition:.3g})" if np.isfinite(condition) else "")
        + f"; {fix}.",
        condition=condition, tol=tol, suggested_tol=cand)


def _check_left_invertible(A, B, C, As, Bs, Cs, QV, QS, tol, suggest: bool) -> None:
    n, k = Bs.shape
    rB = sub.rank(Bs, tol)
    n_a = QV.shape[1]
    dim_int = n_a + rB - sub.rank(np.hstack([QV, Bs]), tol) if rB else 0
    VS = np.hstack([QV, QS])
    overlap = VS.shape[1] > 0 and sub.rank(VS, tol) < VS.shape[1]
    if not (rB < k or dim_int > 0 or overlap):
        return
    nrank = normal_rank(As, Bs, Cs)
    if nrank == n + k:                               # structurally fine: a numerical failure
        sv = np.linalg.svd(VS if overlap else np.hstack([QV, Bs]), compute_uv=False)
        cond = 1.0 / max(float(sv[-1]), np.finfo(float).tiny) if sv.size else np.inf
        what = ("V* and S* are numerically indistinguishable (the smallest angle between them "
                f"has sine {1 / cond:.1e} < tol)" if overlap else
                "V* ∩ im B looks nonzero at this tolerance")
        raise _ill_conditioned(A, B, C, tol, cond, what, suggest)
    if rB < k or dim_int > 0:
        why = []
        if rB < k:
            why.append(f"B has rank {rB} < {k} columns (two inputs act alike: remove or "
                       "combine them)")
        if dim_int > 0:
            why.append(f"dim(V* ∩ im B) = {dim_int} > 0 (an input direction can act "
                       "without ever reaching the output)")
        nrank = normal_rank(As, Bs, Cs)
        raise NotLeftInvertibleError(
            "the triple (C, A, B) is not left-invertible: " + "; ".join(why) +
            f". Normal rank of the Rosenbrock matrix {nrank} < n + k = {n + k}. "
            "Assumption 1 requires a left-invertible (C, A, E): add outputs that see the "
            "perturbation, or reduce the perturbation to the directions the outputs see.",
            rank_B=rB, normal_rank=nrank, dim_intersection=dim_int)
    raise NotLeftInvertibleError(
        f"the triple (C, A, B) is not left-invertible: V* ∩ S* ≠ 0 and the Rosenbrock matrix "
        f"has normal rank {nrank} < n + k = {n + k}. Add outputs that see the perturbation.",
        rank_B=rB, normal_rank=nrank, dim_intersection=1)


def _chain_tops(Cs: FloatArray, seq: list[FloatArray], tol: float
                ) -> tuple[list[tuple[int, FloatArray]], FloatArray]:
    """Output directions of the chain tops (ascending length) and U2, the γ_b directions.

    A chain of length L has its top w in O_{L−1} ⊖ O_L with O_m = {w : wᵀ C S_m = 0}.
    """
    r = Cs.shape[0]
    mu = len(seq)
    dims = [0] + [S.shape[1] for S in seq]
    at_least = [dims[i] - dims[i - 1] for i in range(1, mu + 1)] + [0]  # chains of length ≥ i
    O = [np.eye(r)] + [sub.null((Cs @ S).T, tol) for S in seq]          # O_0 … O_mu
    tops: list[tuple[int, FloatArray]] = []
    for L in range(1, mu + 1):
        count = at_least[L - 1] - at_least[L]
        W = sub.complement(O[L], within=O[L - 1], tol=tol)
        if W.shape[1] != count:
            raise DimensionError(
                f"SCB: found {W.shape[1]} output directions for chains of length {L} but the "
                f"subspace dimensions predict {count}; the rank decisions are inconsistent at "
                f"tol={tol:g}. Try another tolerance (scb(..., tol=...)).")
        tops.extend((L, W[:, j]) for j in range(count))
    return tops, O[mu]


def _chain_rows(A: FloatArray, C: FloatArray, j: int, W: FloatArray, lengths: tuple[int, ...],
                seq: list[FloatArray], tol: float, top: FloatArray | None = None) -> FloatArray:
    """Rows T_1 … T_L of chain j: T_1 = topᵀC and T_{i+1} = T_i A − aᵀ W C.

    W (k × r) holds the output directions of all chain tops (γ_q = W y), so the injection aᵀWC
    is from chain tops only, never from γ_b, as (6c) requires. a is forced on the tops of
    chains shorter than L − i (so that T_{i+1} annihilates S_{L−i−1}, which keeps non-last
    rows free of δ, χ_a and χ_b; minimum-norm solution) and free on the tops of the other
    chains that are longer; the free part makes T_{i+1} as small as possible (keeps cond Γs
    low). A chain never injects its own top, so SISO chains are pure shifts as in (5). The
    rows are linear in ``top`` (default W[j]), which ``_optimise_tops`` exploits.
    """
    L = lengths[j]
    cscale = np.linalg.norm(C, 2)
    WC = W @ C
    rows = [(W[j] if top is None else top) @ C]
    for i in range(1, L):
        nxt = rows[-1] @ A
        m = L - i - 1
        if m >= 1:
            S = seq[m - 1]
            U, s, Vh = np.linalg.svd(WC @ S, full_matrices=False)
            keep = s > tol * cscale
            a = U[:, keep] @ ((Vh[keep] @ (nxt @ S)) / s[keep])     # min-norm, forced part
            nxt = nxt - a @ WC
        free = [jj for jj, L2 in enumerate(lengths) if jj != j and L2 > m]
        if free:
            G = WC[free]
            z = np.linalg.lstsq(G.T, nxt, rcond=None)[0]
            nxt = nxt - z @ G
        rows.append(nxt)
    return np.vstack(rows)


#: Sweeps of the top optimisation (each chain's γ_b offset given the others'); two suffice in
#: practice, the first already removes most of the growth.
TOP_SWEEPS = 2


def _optimise_tops(A: FloatArray, C: FloatArray, W: FloatArray, U2: FloatArray,
                   lengths: tuple[int, ...], seq: list[FloatArray], tol: float) -> FloatArray:
    """Add γ_b directions to the chain tops (w_j → w_j + U2 c_j) to keep chain rows small.

    Any output direction that annihilates S* may be added to a chain top without changing the
    structure; differentiating the χ_b part it brings along makes the rows grow like ‖A_b‖^i.
    The rows of chain j are linear in c_j, so c_j minimising Σ_i ‖T_i‖² is a least-squares
    problem; the chains are swept ``TOP_SWEEPS`` times because each injects the others' tops.
    """
    r_b = U2.shape[1]
    if r_b == 0:
        return W
    W = W.copy()
    for _ in range(TOP_SWEEPS):
        for j in range(len(lengths)):
            R0 = _chain_rows(A, C, j, W, lengths, seq, tol)
            M = np.stack([_chain_rows(A, C, j, W, lengths, seq, tol, top=U2[:, l]).ravel()
                          for l in range(r_b)], axis=1)
            c = np.linalg.lstsq(M, -R0.ravel(), rcond=None)[0]
            W[j] = W[j] + U2 @ c
    return W


def _decouple_ab(P: FloatArray, Q: FloatArray, A_b: FloatArray, C_b: FloatArray
                 ) -> FloatArray:
    """M with P M − M (A_b + K C_b) = Q, for the K that keeps M small (step 5 of the note).

    T_a = T_a0 + M T_b, so a large M makes the a-rows nearly parallel to the b-rows and
    cond Γs large; ‖M‖ ≲ ‖Q‖ / sep(P, A_b + K C_b). Two candidates are tried: K = 0, and a K
    that moves eig(A_b + K C_b) onto the real axis to the right of every zero (K only serves
    the construction; L_ab is read off the result). The smaller M wins.
    """
    n_a, n_b = Q.shape
    if n_a == 0 or n_b == 0:
        return np.zeros((n_a, n_b))
    za = np.linalg.eigvals(P)
    candidates = [A_b]
    if C_b.shape[0] > 0:
        from scipy.signal import place_poles
        scale = max(1.0, float(np.max(np.abs(za))), float(np.linalg.norm(A_b, 2)))
        base = float(np.max(za.real)) + scale
        poles = base * (1.0 + np.arange(n_b) / max(n_b, 1))
        try:
            with warnings.catch_warnings():   # an approximate placement is all we need:
                warnings.simplefilter("ignore")   # the smaller-M rule below guards the result
                K = -place_poles(A_b.T, C_b.T, poles, maxiter=3).gain_matrix.T
            candidates.append(A_b + K @ C_b)
        except (ValueError, np.linalg.LinAlgError):  # pragma: no cover - placement refused
            pass
    best = None
    for F in candidates:
        try:
            M = sla.solve_sylvester(P, -F, Q)
        except (ValueError, np.linalg.LinAlgError):  # pragma: no cover - common eigenvalue
            continue
        if np.all(np.isfinite(M)) and (best is None or np.linalg.norm(M) < np.linalg.norm(best)):
            best = M
    if best is None:  # pragma: no cover
        raise DimensionError("SCB: cannot decouple χ_a from χ_b (A_a and A_b share an "
                             "eigenvalue and C_b cannot move it); try another tol.")
    return best


def _equilibrate(Ta, Tb, Tq, Wq, lengths):
    """Use the SCB's free scalings to balance the rows of Γs⁻¹ (lowers cond Γs).

    Each chain may be scaled as a whole (with its output direction), and each a- and b-row
    individually; all are brought to τ, the geometric mean of the chain-row norms.
    """
    logn = np.log(np.linalg.norm(Tq, axis=1))
    tau = float(np.exp(np.mean(logn)))
    Tq, Wq = Tq.copy(), Wq.copy()
    start = 0
    for j, L in enumerate(lengths):
        c = tau / float(np.exp(np.mean(logn[start:start + L])))
        Tq[start:start + L] *= c
        Wq[j] *= c
        start += L

    def rows_to(T):
        nr = np.linalg.norm(T, axis=1)
        return T * (tau / np.where(nr > 0, nr, 1.0))[:, None]

    return rows_to(Ta), rows_to(Tb), Tq, Wq


def scb(A, B, C, *, tol: float | None = None) -> SCBResult:
    """Special coordinate basis of a strictly proper, left-invertible triple (Sec. III).

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, k)
        Full column rank (in the paper, B is E of the error system (4)).
    C : array_like, shape (r, n)
        Full row rank, r ≥ k.
    tol : float, optional
        Singular-value tolerance for rank decisions on data normalised to unit norm
        (default ``DEFAULT_TOL`` = 1e-10).

    Returns
    -------
    SCBResult
        Transforms, structure, the blocks of (6), cond(Γs) and the residual of the pattern.

    Raises
    ------
    NotLeftInvertibleError
        The triple is not left-invertible: the Rosenbrock matrix lacks full normal rank (the
        robust test of :func:`~thetahat.structure.zeros.is_left_invertible`); the message
        gives rank B, dim(V* ∩ im B) and the normal rank.
    IllConditionedError
        The triple is left-invertible but its SCB cannot be built at ``tol`` (V* and S*
        numerically indistinguishable, inconsistent rank decisions, or a failed pattern
        check); the message gives the condition estimate and a tolerance that works, if any.
    DimensionError
        Wrong shapes, or C without full row rank (the message names the redundant rows).

    Warns
    -----
    IllConditionedWarning
        If cond(Γs) > ``COND_WARN`` (consider designing on a simplified system, Sec. VII).

    Examples
    --------
    A double integrator seen through its position (relative degree 2, no zeros):

    >>> from thetahat import scb
    >>> res = scb([[0, 1], [0, 0]], [[0], [1]], [[1, 0]])
    >>> res.n_a, res.n_b, res.chain_lengths
    (0, 0, (2,))
    """
    A, B, C = as_triple(A, B, C)
    tol = DEFAULT_TOL if tol is None else float(tol)
    if not (np.isfinite(tol) and 0 < tol < 1):
        raise DimensionError(f"tol must be a number in (0, 1); got {tol!r}.")
    if B.shape[1] == 0:
        raise DimensionError("B must have at least one column (k >= 1).")
    _check_output_rank(C, tol)
    try:
        return _scb(A, B, C, tol, suggest=True)
    except DimensionError as exc:        # a numerical failure after the structural checks
        raise _ill_conditioned(A, B, C, tol, float("nan"), str(exc), True) from exc


def _check_output_rank(C: FloatArray, tol: float) -> None:
    """Refuse redundant outputs, naming the rank and the rows to drop."""
    r = C.shape[0]
    Cs = _normalised(C)
    rank_C = sub.rank(Cs, tol)
    if rank_C == r:
        return
    _, _, piv = sla.qr(Cs.T, pivoting=True, mode="economic")
    keep = sorted(int(i) for i in piv[:rank_C])
    drop = sorted(int(i) for i in piv[rank_C:])
    raise DimensionError(
        f"C has rank {rank_C} < {r} rows: outputs {drop} are linear combinations of outputs "
        f"{keep} (redundant sensors). Keep the independent rows, C[{keep}, :] (and the same "
        f"columns of y), before the SCB or a design: the observer needs C of full row rank.")


def _scb(A: FloatArray, B: FloatArray, C: FloatArray, tol: float, *, suggest: bool
         ) -> SCBResult:
    n, k = B.shape
    As, Bs, Cs = _normalised(A), _normalised(B), _normalised(C)
    QV = sub.largest_output_nulling(As, Bs, Cs, tol)
    seq = sub.input_containing_sequence(As, Bs, Cs, tol)
    QS = seq[-1]
    _check_left_invertible(A, B, C, As, Bs, Cs, QV, QS, tol, suggest)
    n_a, n_q = QV.shape[1], QS.shape[1]
    n_b = n - n_a - n_q

    tops, U2 = _chain_tops(Cs, seq, tol)
    lengths = tuple(L for L, _ in tops)
    Wq = _optimise_tops(A, C, np.vstack([w for _, w in tops]), U2, lengths, seq, tol)
    Tq = np.vstack([_chain_rows(A, C, j, Wq, lengths, seq, tol) for j in range(len(tops))])
    last = np.cumsum(lengths) - 1                               # last row of each chain in Tq

    Tb = sub.complement(sub.orth(np.hstack([QV, QS]), tol), tol=tol).T      # ann(V* + S*)
    Ta0 = sub.complement(np.hstack([QS, Tb.T])).T       # completes ann(S*); Tb ⊥ S* already
    if Ta0.shape[0] != n_a or Tb.shape[0] != n_b:  # pragma: no cover
        raise DimensionError("SCB: inconsistent subspace dimensions; try another tol.")

    WqC = Wq @ C
    basis = np.vstack([Ta0, Tb, WqC])
    coef_b = np.linalg.lstsq(basis.T, (Tb @ A).T, rcond=None)[0].T
    A_b0 = coef_b[:, n_a:n_a + n_b]
    coef_a = np.linalg.lstsq(basis.T, (Ta0 @ A).T, rcond=None)[0].T
    P, Q = coef_a[:, :n_a], coef_a[:, n_a:n_a + n_b]
    C_b0 = (U2.T @ C) @ Tb.T
    M = _decouple_ab(P, Q, A_b0, C_b0)
    Ta = Ta0 + M @ Tb

    Ta, Tb, Tq, Wq = _equilibrate(Ta, Tb, Tq, Wq, lengths)
    Tinv = np.vstack([Ta, Tb, Tq])
    Gs = np.linalg.solve(Tinv, np.eye(n))
    Gi = np.linalg.solve(Tq[last] @ B, np.eye(k))
    Go_inv = np.vstack([Wq, U2.T])
    Go = np.linalg.solve(Go_inv, np.eye(Go_inv.shape[0]))
    At, Bt, Ct = Tinv @ A @ Gs, Tinv @ B @ Gi, Go_inv @ C @ Gs
    return _assemble(A, B, C, At, Bt, Ct, Gs, Go, Gi, n_a, n_b, lengths, tol)


def _pattern(n_a: int, n_b: int, lengths: tuple[int, ...], r: int):
    """Masks of the entries (6) leaves free in Ã and C̃, and the fixed B̃, C̃ structure."""
    k = len(lengths)
    n = n_a + n_b + sum(lengths)
    starts = n_a + n_b + np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(int)
    tops = starts
    lasts = starts + np.array(lengths) - 1
    free = np.zeros((n, n), bool)
    ia, ib = slice(0, n_a), slice(n_a, n_a + n_b)
    free[ia, ia] = True
    free[ia, ib] = True      # only as L_ab C_b: checked separately
    free[np.ix_(range(n_a), tops)] = True
    free[ib, ib] = True
    free[np.ix_(range(n_a, n_a + n_b), tops)] = True
    shift = np.zeros((n, n))
    for j, (s, L) in enumerate(zip(starts, lengths)):
        others = [t for jj, t in enumerate(tops) if jj != j]   # never its own top (see rows)
        for i in range(L - 1):
            free[np.ix_([s + i], others)] = True
            shift[s + i, s + i + 1] = 1.0
    free[lasts, :] = True
    Bpat = np.zeros((n, k))
    Bpat[lasts, np.arange(k)] = 1.0
    Cpat = np.zeros((r, n))
    Cpat[np.arange(k), tops] = 1.0
    return free, shift, Bpat, Cpat, tops, lasts


def _assemble(A, B, C, At, Bt, Ct, Gs, Go, Gi, n_a, n_b, lengths, tol) -> SCBResult:
    n, k, r = A.shape[0], B.shape[1], C.shape[0]
    free, shift, Bpat, Cpat, tops, lasts = _pattern(n_a, n_b, lengths, r)
    ib = slice(n_a, n_a + n_b)
    C_b = Ct[k:, ib]
    # L_ab: least-squares fit of the a–b block by L_ab C_b (the a-rows see b only through γ_b)
    L_ab = (np.linalg.lstsq(C_b.T, At[:n_a, ib].T, rcond=None)[0].T if n_b and r > k
            else np.zeros((n_a, r - k)))
    A_clean = np.where(free, At, 0.0) + shift * (~free)
    A_clean[:n_a, ib] = L_ab @ C_b
    C_clean = Cpat.copy()
    C_clean[k:, ib] = C_b

    def rel(X, Y):
        d = np.max(np.abs(X - Y)) if X.size else 0.0
        return d / max(1.0, np.max(np.abs(Y)) if Y.size else 1.0)

    residual = max(rel(At, A_clean), rel(Bt, Bpat), rel(Ct, C_clean))
    if residual > RESIDUAL_FAIL:
        raise DimensionError(
            f"SCB construction failed the pattern check (relative residual {residual:.2e} > "
            f"{RESIDUAL_FAIL:g}); the rank decisions at tol={tol:g} are probably wrong for this "
            "data. Try a different tolerance via scb(..., tol=...).")

    A_a = A_clean[:n_a, :n_a]
    zeros = np.sort_complex(np.linalg.eigvals(A_a).astype(complex)) if n_a else np.zeros(0, complex)
    scale = max(1.0, float(np.linalg.norm(A, 2)))
    minimum_phase = unstable_zeros(zeros, scale=scale).size == 0
    cond = float(np.linalg.cond(Gs))
    if cond > COND_WARN:
        warnings.warn(
            f"SCB state transform is ill-conditioned (cond Γs = {cond:.2e}). Derivative "
            "coordinates are ill-conditioned by nature; if a small parameter lowers the "
            "relative degree, design the gains on the simplified system instead (Sec. VII).",
            IllConditionedWarning, stacklevel=3)
    q = slice(n_a + n_b, n)
    L_qq = A_clean[q][:, tops].copy()
    L_qq[lasts - n_a - n_b] = 0.0
    for M in (A_clean, Bpat, C_clean, Gs, Go, Gi):
        M.setflags(write=False)
    return SCBResult(
        n_a=n_a, n_b=n_b, chain_lengths=tuple(int(L) for L in lengths),
        invariant_zeros=zeros, minimum_phase=bool(minimum_phase),
        state_transform=Gs, output_transform=Go, input_transform=Gi,
        A_tilde=A_clean, B_tilde=Bpat, C_tilde=C_clean,
        A_a=A_a.copy(), L_aq=A_clean[:n_a][:, tops].copy(), L_ab=L_ab,
        A_b=A_clean[ib, ib].copy(), L_bq=A_clean[ib][:, tops].copy(), C_b=C_b.copy(),
        L_qq=L_qq, D_a=A_clean[lasts, :n_a].copy(), D_b=A_clean[lasts, ib].copy(),
        D_q=A_clean[lasts][:, q].copy(), condition=cond, residual=float(residual), tol=tol)
