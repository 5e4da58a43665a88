"""The steps of the update laws of Propositions 1–4 and of the projection, written once.

Like :mod:`~thetahat.estimation.observer.formulas`, these are plain functions over the primitives of
:mod:`~thetahat.estimation.kernels.primitives`; the NumPy laws
(:class:`~thetahat.estimation.observer.laws.inversion.IntermittentInversion`,
:class:`~thetahat.estimation.observer.laws.gradient.GradientInversion`,
:class:`~thetahat.estimation.observer.laws.base.ConstantLaw`) run them bound to NumPy (their ``step``
validates the inputs, then calls the bound formula), and the compiled observer emits the same
functions with the scalar primitives.

A law's step has the signature ``law(LP, v, x, xo, phi, th, to, dt, thn, lsn)``: v, x̂ =
x[xo:], φ̂, θ̂ = th[to:] and the step length in, θ̂⁺ (and the law state, none of the laws
here has one) out; ``LP`` holds the law's arrays and scratch. It returns ``ST_OK`` (0), or
``ST_THETA_STAR`` (:class:`~thetahat.estimation.status.Status`) when θ* is NaN or inf in some
row while the weight is positive (``on_invalid='raise'``).

Free names a binding provides, besides the primitives: ``weight(LP, v, x, xo, phi)``
(the excitation weight l, or 1), ``theta_star(v, x, xo, phi, ts)``, ``g_val``, ``dg_dtheta`` (as in
:mod:`~thetahat.estimation.observer.formulas`), ``m_matrix(v, x, xo, th, to, Mt)`` (a user's M of
Proposition 3, with ``USER_M``), ``project(LP, thn)`` (the Γ⁻¹-weighted projection onto Θ in
place; returns 0), ``freeze(LP)`` (``on_invalid == 'freeze'``), the constants ``NP``, ``NK``,
``USER_M``, ``FAR`` (:data:`~thetahat.estimation.observer.laws.base.FAR`) and ``ST_THETA_STAR``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                    # the argument tuples (named; every binding builds them)
    from ...kernels.kernel_args import LawArrays

__all__ = ["LAW_FORMULAS", "finite_candidate", "gradient_law", "held_law", "inversion_law",
           "inversion_target", "smoothstep"]

# Names bound by a back end (declared for the type checker; never assigned here).
Prim = Callable[..., Any]
get: Prim
put: Prim
get2: Prim
put2: Prim
copy: Prim
fill: Prim
mv: Prim
mm: Prim
mmt: Prim
expm: Prim
where: Prim
clip: Prim
exp: Prim
isfinite: Prim
isnan: Prim
not_: Prim
and_: Prim
or_: Prim
count_: Prim
weight: Prim
theta_star: Prim
g_val: Prim
dg_dtheta: Prim
m_matrix: Prim
project: Prim
NP: int
NK: int
freeze: Prim
USER_M: bool
FAR: float
ST_THETA_STAR: int


def smoothstep(s: Any, low: float, high: float) -> Any:
    """0 for s <= low, 1 for s >= high, 3t² − 2t³ with t = (s − low)/(high − low) between.

    The excitation weight of :func:`~thetahat.estimation.observer.laws.inversion.smooth_ramp` (Remark 5).

    Parameters
    ----------
    s : float or array
    low, high : float

    Returns
    -------
    float or array
    """
    t = clip((s - low) / (high - low), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def finite_candidate(p: int, cand: Any, th: Any, to: int) -> None:
    """In place: NaN entries of ``cand`` → θ̂ (th[to:]), ±inf and huge values → ±FAR.

    So that the projection can handle every candidate.

    Parameters
    ----------
    p : int
    cand : array
        Candidate θ before the projection (overwritten).
    th : array
    to : int
    """
    for i in range(p):
        c = get(cand, i)
        put(cand, i, clip(where(isnan(c), get(th, to + i), c), -FAR, FAR))


def held_law(LP: LawArrays, v: Any, x: Any, xo: int, phi: Any, th: Any, to: int,
             dt: float, thn: Any, lsn: Any) -> int:
    """θ̂̇ = 0 (:class:`~thetahat.estimation.observer.laws.base.ConstantLaw`): θ̂, projected onto Θ.

    Parameters
    ----------
    LP : tuple
        What ``project`` reads.
    v, x, phi, th : array
    xo, to : int
    dt : float
    thn, lsn : array
        θ̂⁺ and the law state (unused).

    Returns
    -------
    int
    """
    copy(NP, th, to, thn, 0)
    return project(LP, thn)


def inversion_target(LP: LawArrays, v: Any, x: Any, xo: int, phi: Any, th: Any,
                     to: int, ts: Any) -> tuple[int, Any]:
    """The target of Propositions 1–2 and the weight: θ* into ``ts``, θ̂ where l = 0.

    θ* may be NaN or inf where l = 0. Where l > 0 but θ* is not finite, ``freeze`` sets l = 0
    (θ̂ is held there); otherwise the caller reports the rows counted.

    Parameters
    ----------
    LP : tuple
        What the hooks read.
    v, x, phi, th : array
    xo, to : int
    ts : array
        Output: the target.

    Returns
    -------
    nbad : int
        Rows where l > 0 and θ* is NaN or inf.
    lw : float or array
        The weight l (0 on those rows with ``freeze``).
    """
    lw = weight(LP, v, x, xo, phi)
    theta_star(v, x, xo, phi, ts)
    invalid = False
    for i in range(NP):
        invalid = or_(invalid, not_(isfinite(get(ts, i))))
    invalid = and_(invalid, lw > 0.0)
    nbad = count_(invalid)
    if nbad > 0 and freeze(LP):
        lw = where(invalid, 0.0, lw)
    active = lw > 0.0
    for i in range(NP):
        put(ts, i, where(active, get(ts, i), get(th, to + i)))
    return nbad, lw


def inversion_law(LP: LawArrays, v: Any, x: Any, xo: int, phi: Any, th: Any, to: int,
                  dt: float, thn: Any, lsn: Any) -> int:
    """Propositions 1–2: the exact flow of θ̇ = lΓ(θ* − θ) over dt, then the projection.

    With l and θ* held over the step, θ̂⁺ = θ* − V e^(−l dt Λ) Vᵀ (θ* − θ̂) for Γ = V Λ Vᵀ; θ* is
    replaced by θ̂ where l = 0 (so that it may be NaN there), and where l > 0 but θ* is NaN or
    inf the step reports it, or holds θ̂ (l ← 0) with ``freeze``.

    Parameters
    ----------
    LP : tuple
        (Λ, V, Vᵀ, θ* scratch, scratch, …): the eigen-decomposition of Γ (one per row or shared)
        and what ``project`` reads.
    v, x, phi, th : array
    xo, to : int
    dt : float
    thn, lsn : array

    Returns
    -------
    int
    """
    lam, V, VT, ts, err = LP.lam, LP.V, LP.VT, LP.ts, LP.err
    p = NP
    nbad, lw = inversion_target(LP, v, x, xo, phi, th, to, ts)
    if nbad > 0 and not freeze(LP):
        return ST_THETA_STAR
    for i in range(p):
        put(err, i, get(ts, i) - get(th, to + i))
    mv(VT, p, p, err, 0, thn, 0, 0)                 # Vᵀ (θ* − θ̂)
    for i in range(p):
        put(err, i, exp(-lw * dt * get(lam, i)) * get(thn, i))
    mv(V, p, p, err, 0, thn, 0, 0)
    for i in range(p):
        put(thn, i, get(ts, i) - get(thn, i))
    finite_candidate(p, thn, th, to)
    return project(LP, thn)


def gradient_law(LP: LawArrays, v: Any, x: Any, xo: int, phi: Any, th: Any, to: int,
                 dt: float, thn: Any, lsn: Any) -> int:
    """Propositions 3–4: exponential Euler on θ̇ = ΓM(φ̂ − g(v, x̂, θ)), then the projection.

    With K = ΓM ∂g/∂θ and f = ΓM(φ̂ − g) at θ̂ the linearisation θ̇ = f − K(θ − θ̂) is integrated
    exactly over dt: the last column of exp([[−dt K, dt f], [0, 0]]). Where that is not finite
    the step falls back to Euler (±FAR where f is infinite).

    Parameters
    ----------
    LP : tuple
        (Γ, g, ∂g/∂θ, M, ΓM, f, K, Z, e^Z, scratch, scratch, …): Γ (one per row or shared),
        scratch, and what ``project`` reads.
    v, x, phi, th : array
    xo, to : int
    dt : float
    thn, lsn : array

    Returns
    -------
    int
    """
    Gam, g, J, Mt, GM, f, K = LP.Gamma, LP.g, LP.J, LP.Mt, LP.GM, LP.f, LP.K
    Z, Ex, T, U = LP.Z, LP.Ex, LP.T, LP.U
    p, k = NP, NK
    g_val(v, x, xo, th, to, g)
    dg_dtheta(v, x, xo, th, to, J)
    if USER_M:
        m_matrix(v, x, xo, th, to, Mt)
        mm(Gam, Mt, p, p, k, GM, 0, 0, 0)
    else:
        mmt(Gam, J, p, p, k, GM)                    # ΓM with M = (∂g/∂θ)ᵀ
    for a in range(k):
        put(g, a, get(phi, a) - get(g, a))          # φ̂ − g
    mv(GM, p, k, g, 0, f, 0, 0)
    mm(GM, J, p, k, p, K, 0, 0, 0)
    fill(Z, 0.0)
    ok = True
    for a in range(p):
        for c in range(p):
            put2(Z, a, c, -dt * get2(K, a, c))
            ok = and_(ok, isfinite(get2(Z, a, c)))
        put2(Z, a, p, dt * get(f, a))
        ok = and_(ok, isfinite(get2(Z, a, p)))
    for a in range(p):
        for c in range(p + 1):
            put2(Z, a, c, where(ok, get2(Z, a, c), 0.0))
    expm(p + 1, Z, Ex, T, U)
    for a in range(p):
        ok = and_(ok, isfinite(get2(Ex, a, p)))
    for a in range(p):
        fa = get(f, a)
        euler = where(isfinite(fa), dt * fa, where(fa > 0.0, FAR, where(fa < 0.0, -FAR, 0.0)))
        put(thn, a, get(th, to + a) + where(ok, get2(Ex, a, p), euler))
    finite_candidate(p, thn, th, to)
    return project(LP, thn)


#: The law formulas a back end binds, by name.
LAW_FORMULAS: dict[str, Callable[..., Any]] = {
    "smoothstep": smoothstep, "finite_candidate": finite_candidate, "held_law": held_law,
    "inversion_target": inversion_target, "inversion_law": inversion_law,
    "gradient_law": gradient_law}
