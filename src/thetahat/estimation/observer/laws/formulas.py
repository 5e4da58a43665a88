"""The steps of the update laws of Propositions 1–4 and of the projection, written once.

Like :mod:`~thetahat.estimation.observer.formulas`, these are plain functions in the formulas'
language (:mod:`~thetahat.estimation.kernels.subset`); the NumPy laws
(:class:`~thetahat.estimation.observer.laws.inversion.IntermittentInversion`,
:class:`~thetahat.estimation.observer.laws.gradient.GradientInversion`,
:class:`~thetahat.estimation.observer.laws.base.ConstantLaw`) run them printed for NumPy (their
``step`` validates the inputs, then calls the printed formula), and the compiled observer and
the C run them printed as scalar loops.

A law's step has the signature ``law(LP, v, x, phi, th, dt, thn, lsn)``: v, x̂, φ̂, θ̂ and the
step length in, θ̂⁺ (and the law state, none of the laws here has one) out; ``LP``
(:class:`~thetahat.estimation.kernels.kernel_args.LawArrays`) holds the law's arrays and
scratch. It returns ``ST_OK`` (0), or ``ST_THETA_STAR``
(:class:`~thetahat.estimation.status.Status`) when θ* is NaN or inf in some row while the
weight is positive (``on_invalid='raise'``).

Free names a binding provides, besides the vocabulary: ``weight(LP, v, x, phi)`` (the
excitation weight l, or 1), ``theta_star(v, x, phi, ts)``, ``g_val``, ``dg_dtheta`` (as in
:mod:`~thetahat.estimation.observer.formulas`), ``m_matrix(v, x, th, Mt)`` (a user's M of
Proposition 3, with ``USER_M``), ``project(LP, thn)`` (the Γ⁻¹-weighted projection onto Θ in
place; returns 0), ``freeze(LP)`` (``on_invalid == 'freeze'``), the constants ``NP``, ``NK``,
``USER_M``, ``FAR`` (:data:`~thetahat.estimation.observer.laws.base.FAR`) and ``ST_THETA_STAR``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                    # the argument tuples (named; every binding builds them)
    from ...kernels.kernel_args import LawArrays

__all__ = ["HOOKS", "LAW_FORMULAS", "finite_candidate", "gradient_law", "held_law", "inversion_law",
           "inversion_target", "least_squares_law", "smoothstep"]

#: The functions the law formulas call that a binding provides, with their parameters
#: (module docstring); ``x`` and ``th`` take views of the state
#: (:data:`~thetahat.estimation.observer.formulas.VIEWED`).
HOOKS = {"weight": ("LP", "v", "x", "phi"), "theta_star": ("v", "x", "phi", "ts"),
         "g_val": ("v", "x", "th", "g"), "dg_dtheta": ("v", "x", "th", "Gth"),
         "m_matrix": ("v", "x", "th", "Mt"), "project": ("LP", "thn"), "freeze": ("LP",)}

# Names bound by a back end (declared for the type checker; never assigned here).
Prim = Callable[..., Any]
expm: Prim
eye: Prim
solve: Prim
any_: Prim
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
freeze: Prim
NP: int
NK: int
NX: int
NQ: int
USER_M: bool
FAR: float
ST_THETA_STAR: int
ST_OK: int
ST_SINGULAR: int


def smoothstep(s: Any, low: float, high: float) -> Any:
    """0 for s <= low, 1 for s >= high, 3t² − 2t³ with t = (s − low)/(high − low) between.

    The excitation weight of :func:`~thetahat.estimation.observer.laws.inversion.smooth_ramp`
    (Remark 5).

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


def finite_candidate(cand: Any, th: Any) -> None:
    """In place: NaN entries of ``cand`` → θ̂, ±inf and huge values → ±FAR.

    So that the projection can handle every candidate.

    Parameters
    ----------
    cand : array, shape (NP,)
        Candidate θ before the projection (overwritten).
    th : array, shape (NP,)
        θ̂.
    """
    for i in range(NP):
        c = cand[i]
        cand[i] = clip(where(isnan(c), th[i], c), -FAR, FAR)


def held_law(LP: LawArrays, v: Any, x: Any, phi: Any, th: Any, dt: float, thn: Any,
             lsn: Any) -> int:
    """θ̂̇ = 0 (:class:`~thetahat.estimation.observer.laws.base.ConstantLaw`): θ̂, projected
    onto Θ.

    Parameters
    ----------
    LP : LawArrays
        What ``project`` reads.
    v : array, shape (NV,)
    x : array, shape (NX,)
    phi : array, shape (NK,)
    th : array, shape (NP,)
        v, x̂, φ̂, θ̂.
    dt : float
    thn : array, shape (NP,)
        Output: θ̂⁺.
    lsn : array
        The law state (unused).

    Returns
    -------
    int
    """
    thn[:] = th
    return project(LP, thn)


def inversion_target(LP: LawArrays, v: Any, x: Any, phi: Any, th: Any, ts: Any
                     ) -> tuple[int, Any]:
    """The target of Propositions 1–2 and the weight: θ* into ``ts``, θ̂ where l = 0.

    θ* may be NaN or inf where l = 0. Where l > 0 but θ* is not finite, ``freeze`` sets l = 0
    (θ̂ is held there); otherwise the caller reports the rows counted.

    Parameters
    ----------
    LP : LawArrays
        What the hooks read.
    v : array, shape (NV,)
    x : array, shape (NX,)
    phi : array, shape (NK,)
    th : array, shape (NP,)
    ts : array, shape (NP,)
        Output: the target.

    Returns
    -------
    nbad : int
        Rows where l > 0 and θ* is NaN or inf.
    lw : float or array
        The weight l (0 on those rows with ``freeze``).
    """
    lw = weight(LP, v, x, phi)
    theta_star(v, x, phi, ts)
    invalid = False
    for i in range(NP):
        invalid = or_(invalid, not_(isfinite(ts[i])))
    invalid = and_(invalid, lw > 0.0)
    nbad = count_(invalid)
    if nbad > 0 and freeze(LP):
        lw = where(invalid, 0.0, lw)
    active = lw > 0.0
    for i in range(NP):
        ts[i] = where(active, ts[i], th[i])
    return nbad, lw


def inversion_law(LP: LawArrays, v: Any, x: Any, phi: Any, th: Any, dt: float, thn: Any,
                  lsn: Any) -> int:
    """Propositions 1–2: the exact flow of θ̇ = lΓ(θ* − θ) over dt, then the projection.

    With l and θ* held over the step, θ̂⁺ = θ* − V e^(−l dt Λ) Vᵀ (θ* − θ̂) for Γ = V Λ Vᵀ; θ* is
    replaced by θ̂ where l = 0 (so that it may be NaN there), and where l > 0 but θ* is NaN or
    inf the step reports it, or holds θ̂ (l ← 0) with ``freeze``.

    Parameters
    ----------
    LP : LawArrays
        Λ (``lam``), V, Vᵀ (one per row or shared), the scratch ``ts``, ``err`` and what
        ``project`` reads.
    v : array, shape (NV,)
    x : array, shape (NX,)
    phi : array, shape (NK,)
    th : array, shape (NP,)
    dt : float
    thn : array, shape (NP,)
        Output: θ̂⁺.
    lsn : array
        The law state (unused).

    Returns
    -------
    int
    """
    lam, V, VT, ts, err = LP.lam, LP.V, LP.VT, LP.ts, LP.err
    nbad, lw = inversion_target(LP, v, x, phi, th, ts)
    if nbad > 0 and not freeze(LP):
        return ST_THETA_STAR
    err[:] = ts - th                                 # θ* − θ̂
    thn[:] = VT @ err                                # Vᵀ (θ* − θ̂)
    for i in range(NP):
        err[i] = exp(-lw * dt * lam[i]) * thn[i]
    thn[:] = V @ err
    thn[:] = ts - thn                                # θ* − V e^(−l dt Λ) Vᵀ (θ* − θ̂)
    finite_candidate(thn, th)
    return project(LP, thn)


def gradient_law(LP: LawArrays, v: Any, x: Any, phi: Any, th: Any, dt: float, thn: Any,
                 lsn: Any) -> int:
    """Propositions 3–4: exponential Euler on θ̇ = ΓM(φ̂ − g(v, x̂, θ)), then the projection.

    With K = ΓM ∂g/∂θ and f = ΓM(φ̂ − g) at θ̂ the linearisation θ̇ = f − K(θ − θ̂) is integrated
    exactly over dt: the last column of exp([[−dt K, dt f], [0, 0]]). Where that is not finite
    the step falls back to Euler (±FAR where f is infinite).

    Parameters
    ----------
    LP : LawArrays
        Γ (one per row or shared), the scratch ``g``, ``J``, ``Mt``, ``GM``, ``f``, ``K``,
        ``Z``, ``Ex``, ``T``, ``U`` and what ``project`` reads.
    v : array, shape (NV,)
    x : array, shape (NX,)
    phi : array, shape (NK,)
    th : array, shape (NP,)
    dt : float
    thn : array, shape (NP,)
        Output: θ̂⁺.
    lsn : array
        The law state (unused).

    Returns
    -------
    int
    """
    Gam, g, J, Mt, GM, f, K, Z, Ex = LP.Gamma, LP.g, LP.J, LP.Mt, LP.GM, LP.f, LP.K, LP.Z, LP.Ex
    g_val(v, x, th, g)
    dg_dtheta(v, x, th, J)
    if USER_M:
        m_matrix(v, x, th, Mt)
        GM[:] = Gam @ Mt
    else:
        GM[:] = Gam @ J.T                            # ΓM with M = (∂g/∂θ)ᵀ
    g[:] = phi - g                                   # φ̂ − g
    f[:] = GM @ g
    K[:] = GM @ J
    Z[:] = 0.0
    ok = True
    for a in range(NP):
        for c in range(NP):
            Z[a, c] = -dt * K[a, c]
            ok = and_(ok, isfinite(Z[a, c]))
        Z[a, NP] = dt * f[a]
        ok = and_(ok, isfinite(Z[a, NP]))
    for a in range(NP):
        for c in range(NP + 1):
            Z[a, c] = where(ok, Z[a, c], 0.0)
    expm(Z, Ex, LP.T, LP.U)
    for a in range(NP):
        ok = and_(ok, isfinite(Ex[a, NP]))
    for a in range(NP):
        fa = f[a]
        euler = where(isfinite(fa), dt * fa, where(fa > 0.0, FAR, where(fa < 0.0, -FAR, 0.0)))
        thn[a] = th[a] + where(ok, Ex[a, NP], euler)
    finite_candidate(thn, th)
    return project(LP, thn)


def least_squares_law(LP: LawArrays, v: Any, x: Any, phi: Any, th: Any, dt: float, thn: Any,
                      lsn: Any) -> int:
    """The filtered least-squares law: one step of θ̂ and of its state col(w, w_b, a, R).

    :class:`~thetahat.estimation.observer.laws.least_squares.FilteredLeastSquares` (its notes
    give the derivation). With J = ∂g/∂θ, z = φ̂ − g at θ̂, the filtered regressor W = H w and
    ζ = z + a + H w_b (= W θ for g linear in θ), all held over dt:

    R⁺ = R + dt WᵀW (symmetrised), θ̂⁺ = Proj_R⁺(θ̂ + (R⁺)⁻¹ dt Wᵀ(ζ − W θ̂)),
    w⁺ = A_d w + B_d J, w_b⁺ = A_d w_b + B_d (J θ̂ − a), a⁺ = a + J (θ̂⁺ − θ̂),

    with A_d = I + L Φ₁, B_d = Φ₁ G (the last NK columns of Φ₁): the exact step of the error
    filter ẇ = L w + G J. A row whose J or z is not finite takes J = 0 and dt = 0 in R and θ̂:
    θ̂ and R are left as they are and w decays.

    Parameters
    ----------
    LP : LawArrays
        The filter's ``H`` and ``Lf`` (its L), ``Phi1`` (Φ₁ of this step), the scratch ``g``,
        ``J``, ``w``, ``wn``, ``wb``, ``Wm``, ``WT``, ``Rn`` (R⁺, the metric of ``project``),
        ``Rf``, ``b``, ``e``, ``Ad``, ``Bd``, ``q`` and what ``project`` reads.
    v : array, shape (NV,)
    x : array, shape (NX,)
    phi : array, shape (NK,)
    th : array, shape (NP,)
    dt : float
    thn : array, shape (NP,)
        Output: θ̂⁺.
    lsn : array, shape (LS1,)
        The law state col(w (NQ × NP, row-major), w_b (NQ), a (NK), R (NP × NP, row-major)):
        in on entry, out on return.

    Returns
    -------
    int
        ``ST_OK``, or ``ST_SINGULAR`` where R⁺ is singular.
    """
    z, J, H, w, wb, W, WT, Rn, Rf = LP.g, LP.J, LP.H, LP.w, LP.wb, LP.Wm, LP.WT, LP.Rn, LP.Rf
    b, e, Ad, Bd, wn, q = LP.b, LP.e, LP.Ad, LP.Bd, LP.wn, LP.q
    g_val(v, x, th, z)
    dg_dtheta(v, x, th, J)
    ok = True
    for a in range(NK):
        z[a] = phi[a] - z[a]                         # z = φ̂ − g
        ok = and_(ok, isfinite(z[a]))
        for c in range(NP):
            ok = and_(ok, isfinite(J[a, c]))
    h = where(ok, dt, 0.0)                           # the information of this sample
    for a in range(NK):
        z[a] = where(ok, z[a], 0.0)
        for c in range(NP):
            J[a, c] = where(ok, J[a, c], 0.0)
    for i in range(NQ):
        wb[i] = lsn[NQ * NP + i]
        for c in range(NP):
            w[i, c] = lsn[i * NP + c]
    W[:] = H @ w                                     # W = H w
    e[:] = H @ wb
    for a in range(NK):
        e[a] = z[a] + lsn[NQ * NP + NQ + a] + e[a]   # ζ = z + a + H w_b
    e[:] = e - W @ th                                # ζ − W θ̂
    for c in range(NP):
        for a in range(NK):
            WT[c, a] = W[a, c]
    Rf[:] = WT @ W
    for c in range(NP):
        for d in range(NP):
            Rf[c, d] = lsn[NQ * NP + NQ + NK + c * NP + d] + h * Rf[c, d]
    for c in range(NP):
        for d in range(NP):
            Rn[c, d] = 0.5 * (Rf[c, d] + Rf[d, c])     # R⁺ = R + dt WᵀW, symmetric
    Rf[:] = Rn
    b[:] = WT @ e
    for c in range(NP):
        b[c] = h * b[c]
    solved = solve(Rf, b)                            # (R⁺)⁻¹ dt Wᵀ(ζ − W θ̂)
    if any_(solved != ST_OK):
        return ST_SINGULAR
    for c in range(NP):
        thn[c] = th[c] + b[c]
    finite_candidate(thn, th)
    project(LP, thn)                                 # in Θ, in R⁺'s metric
    Ad[:] = eye(NQ) + LP.Lf @ LP.Phi1
    for i in range(NQ):
        for a in range(NK):
            Bd[i, a] = LP.Phi1[i, NX + a]
    e[:] = J @ th
    for a in range(NK):
        e[a] = e[a] - lsn[NQ * NP + NQ + a]          # J θ̂ − a
    q[:] = Ad @ wb + Bd @ e                          # w_b⁺
    wn[:] = Ad @ w + Bd @ J                          # w⁺
    for c in range(NP):
        b[c] = thn[c] - th[c]
    e[:] = J @ b                                     # J (θ̂⁺ − θ̂)
    for i in range(NQ):
        lsn[NQ * NP + i] = q[i]
        for c in range(NP):
            lsn[i * NP + c] = wn[i, c]
    for a in range(NK):
        lsn[NQ * NP + NQ + a] = lsn[NQ * NP + NQ + a] + e[a]
    for c in range(NP):
        for d in range(NP):
            lsn[NQ * NP + NQ + NK + c * NP + d] = Rn[c, d]
    return ST_OK


#: The law formulas a back end prints, by name.
LAW_FORMULAS: dict[str, Callable[..., Any]] = {
    "smoothstep": smoothstep, "finite_candidate": finite_candidate, "held_law": held_law,
    "inversion_target": inversion_target, "inversion_law": inversion_law,
    "gradient_law": gradient_law, "least_squares_law": least_squares_law}
