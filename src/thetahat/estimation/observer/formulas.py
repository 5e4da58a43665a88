"""One sample of observer (3), update law (8) and the second observer of Sec. VI: the definition.

The functions here are the step's formulas, written once over the primitives of
:mod:`~thetahat.estimation.kernels.primitives` (``get``, ``mv``, ``solve``, ``where``, …), the model
functions and a few constants; they hold no data and import nothing they call. Every back end
runs these code objects:

* the Python step and run (one row) and :func:`~thetahat.estimation.observer.batch_run.run_batch`
  (B rows) bind them to the NumPy primitives (:func:`~thetahat.estimation.observer.step.advance`);
* the compiled observer emits their source, with the scalar primitives and the model functions
  printed from SymPy, as one numba module
  (:mod:`~thetahat.estimation.observer.kernel_source`, :mod:`~thetahat.estimation.observer.compiled`).

Free names a binding provides:

* the model functions ``g_dx(v, x, xo, th, to, g, Gx)`` (g and ∂g/∂x at v, x̂ = x[xo:],
  θ̂ = th[to:]), ``g_val(v, x, xo, th, to, g)``, ``dg_dy(v, x, xo, th, to, Gy)`` (the y columns
  of ∂g/∂v), ``dg_dtheta(v, x, xo, th, to, Gth)``;
* ``law_step(LP, v, x, xo, phi, th, to, dt, thn, lsn)``: the update law's step into θ̂⁺
  (``thn``) and the law state (``lsn``, which holds the state at the start on entry); it
  returns 0, or 1 + the number of rows where θ* is invalid under ``on_invalid='raise'``
  (:mod:`~thetahat.estimation.observer.laws.formulas`);
* the dimensions ``NX, NU, NY, NK, NP`` and ``LS`` (law state length), the implicitness γ
  ``IMPLICITNESS``, the divergence bound ``BOUND_SQ`` (:data:`DIVERGENCE_BOUND` squared) and
  the status codes ``ST_<NAME>`` of :class:`~thetahat.estimation.status.Status`.

The state of a row is ``col(x̂, z, θ̂[, x̂₂][, law state])``. The plan tuples:
``P = (L, Bv, E, C, A, B, K_x, K_x C, Φ₁, Φ₂)`` with the φ-matrices of this step (corrected,
or the prediction's over a missing sample), ``P2 = (A, B, C, E, K_x2, Φ₁, Φ₂)`` of the second
observer, and the work buffers ``W`` (:data:`WORK`).

Status codes of :func:`advance` (:class:`~thetahat.estimation.status.Status`): ``ST_OK``;
``ST_DIVERGED`` when φ̂ is not finite; ``ST_THETA_STAR`` when θ* is invalid (the law's);
``ST_SINGULAR`` when an implicit step's matrix is singular (``solve``'s status).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                    # the argument tuples (named; every binding builds them)
    from ..kernels.kernel_args import LawArrays, PlanArrays, SecondArrays

__all__ = ["DIVERGENCE_BOUND", "FORMULAS", "WORK", "advance", "implicit_step",
           "observer_forcing", "observer_jacobian", "second_forcing", "second_jacobian",
           "phi_hat", "second_step",
           "within_bound"]

#: A row of the state has diverged when its Euclidean norm exceeds this (or is not finite).
#: No observer quantity of a sensibly scaled problem comes near it, and its square (1e200)
#: stays finite, so one dot product per step decides. The same rule in every back end makes
#: them report a divergence at the same sample.
DIVERGENCE_BOUND = 1e100

#: The work buffers of :func:`advance`, in order, with their shapes in the dimensions (one
#: row; a back end adds its batch axis).
WORK = (("v", ("NV",)), ("g", ("NK",)), ("Gx", ("NK", "NX")), ("Gy", ("NK", "NY")),
        ("Gth", ("NK", "NP")), ("F", ("NQ",)), ("Fd", ("NQ",)), ("Nm", ("NQ", "NQ")),
        ("M", ("NQ", "NQ")), ("rhs", ("NQ",)), ("phi", ("NK",)), ("wr", ("NY",)),
        ("wn", ("NX",)), ("zc", ("NK",)), ("dth", ("NP",)), ("thn", ("NP",)),
        ("lsn", ("LS1",)), ("v2", ("NV",)), ("g2", ("NK",)), ("Gx2", ("NK", "NX")),
        ("Gy2", ("NK", "NY")), ("F2", ("NX",)), ("Fd2", ("NX",)), ("N2", ("NX", "NX")),
        ("M2", ("NX", "NX")), ("rhs2", ("NX",)), ("w2", ("NY",)))

# Names bound by a back end (declared for the type checker; never assigned here).
Prim = Callable[..., Any]
get: Prim
put: Prim
copy: Prim
axpy: Prim
fill: Prim
mv: Prim
mm: Prim
eye_minus: Prim
solve: Prim
where: Prim
isfinite: Prim
not_: Prim
or_: Prim
any_: Prim
sumsq: Prim
g_dx: Prim
dg_dy: Prim
dg_dtheta: Prim
law_step: Prim
NX: int
NU: int
NY: int
NK: int
NP: int
LS: int
IMPLICITNESS: float
BOUND_SQ: float
ST_OK: int
ST_DIVERGED: int
ST_SINGULAR: int


def observer_forcing(P: PlanArrays, s: Any, u: Any, y: Any, correct: bool, v: Any,
                     g: Any, Gx: Any, F: Any, wr: Any, wn: Any) -> None:
    """F of (3a)–(3b) on (x̂, z) without the θ̂ term; v, g(v, x̂, θ̂) and ∂g/∂x into buffers.

    Measured sample: F = L col(x̂, z) + [[B, K_x], [0, K_φ]] v + col(E g, −∂g/∂x K_x ỹ),
    ỹ = y − C x̂. Missing sample (``correct`` False): v = col(u, C x̂) and
    F = col(A x̂ + B u + E φ̂, 0), φ̂ = g + z.

    Parameters
    ----------
    P : tuple
        The observer's plan arrays (module docstring).
    s : array
        State rows.
    u, y : array
        Samples.
    correct : bool
        The sample y is present.
    v, g, Gx, F, wr, wn : array
        Outputs v, g, ∂g/∂x, F; scratch of lengths r and n.
    """
    L, Bv, E, C, A, Bm, Kx = P.L, P.Bv, P.E, P.C, P.A, P.B, P.K_x
    n, k, m, r = NX, NK, NU, NY
    q = n + k
    copy(m, u, 0, v, 0)
    if correct:
        copy(r, y, 0, v, m)
    else:
        mv(C, r, n, s, 0, v, m, 0)                  # y ← C x̂
    g_dx(v, s, 0, s, q, g, Gx)
    if correct:
        mv(L, q, q, s, 0, F, 0, 0)
        mv(Bv, q, m + r, v, 0, F, 0, 1)
        mv(E, n, k, g, 0, F, 0, 1)
        copy(r, v, m, wr, 0)
        mv(C, r, n, s, 0, wr, 0, -1)                # ỹ = y − C x̂
        mv(Kx, n, r, wr, 0, wn, 0, 0)
        mv(Gx, k, n, wn, 0, F, n, -1)
    else:
        mv(A, n, n, s, 0, F, 0, 0)
        mv(Bm, n, m, u, 0, F, 0, 1)
        mv(E, n, k, g, 0, F, 0, 1)
        mv(E, n, k, s, n, F, 0, 1)                  # E φ̂ = E (g + z)
        for a in range(k):
            put(F, n + a, 0.0)


def observer_jacobian(P: PlanArrays, s: Any, v: Any, correct: bool, Gx: Any, Gy: Any,
                      Nm: Any) -> None:
    """N = [[E ∂g/∂x, 0], [∂g/∂x K_x C, 0]] (measured) or [[E(∂g/∂x + ∂g/∂y C), 0], [0, 0]].

    The linearisation ∂d/∂(x̂, φ̂) of the paper's d without the terms proportional to ỹ and
    θ̂̇. Over a missing sample ``Gx`` is overwritten by ∂g/∂x + ∂g/∂y C.

    Parameters
    ----------
    P : tuple
    s, v : array
        State rows and the v of :func:`observer_forcing`.
    correct : bool
    Gx, Gy : array
        ∂g/∂x (input) and scratch for ∂g/∂y.
    Nm : array
        Output N.
    """
    E, C, KxC = P.E, P.C, P.KxC
    n, k, r = NX, NK, NY
    fill(Nm, 0.0)
    if correct:
        mm(E, Gx, n, k, n, Nm, 0, 0, 0)
        mm(Gx, KxC, k, n, n, Nm, n, 0, 0)
    else:
        dg_dy(v, s, 0, s, n + k, Gy)
        mm(Gy, C, k, r, n, Gx, 0, 0, 1)
        mm(E, Gx, n, k, n, Nm, 0, 0, 0)


def second_forcing(P2: SecondArrays, s: Any, u: Any, y: Any, correct: bool,
                   on_estimates: bool, v2: Any, g2: Any, Gx2: Any, F2: Any, w2: Any) -> None:
    """F = A x̂₂ + B u + E g(v̄, x̂₂, θ̂) + K_x2 (y − C x̂₂) of Sec. VI; v̄, g, ∂g/∂x into buffers.

    v̄ = col(u, C x̂₂) with ``on_estimates`` (the plan's ``g_on_estimates``) or over a missing
    sample (no injection then), else col(u, y); θ̂ is the one at the start of the step.

    Parameters
    ----------
    P2 : tuple
        The second observer's plan arrays.
    s : array
        State rows (x̂₂ after θ̂).
    u, y : array
    correct, on_estimates : bool
    v2, g2, Gx2, F2, w2 : array
        Outputs v̄, g, ∂g/∂x, F; scratch of length r.
    """
    A, Bm, C, E, K2 = P2.A, P2.B, P2.C, P2.E, P2.K_x
    n, k, m, r = NX, NK, NU, NY
    o2 = n + k + NP
    copy(m, u, 0, v2, 0)
    if on_estimates or not correct:
        mv(C, r, n, s, o2, v2, m, 0)
    else:
        copy(r, y, 0, v2, m)
    g_dx(v2, s, o2, s, n + k, g2, Gx2)
    mv(A, n, n, s, o2, F2, 0, 0)
    mv(Bm, n, m, u, 0, F2, 0, 1)
    mv(E, n, k, g2, 0, F2, 0, 1)
    if correct:
        copy(r, y, 0, w2, 0)
        mv(C, r, n, s, o2, w2, 0, -1)
        mv(K2, n, r, w2, 0, F2, 0, 1)


def second_jacobian(P2: SecondArrays, s: Any, v2: Any, correct: bool, on_estimates: bool,
                    Gx2: Any, Gy2: Any, N2: Any) -> None:
    """N = E ∂g/∂x, plus E ∂g/∂y C where g sees C x̂₂ (the exact Jacobian of F in x̂₂).

    Parameters
    ----------
    P2 : tuple
    s, v2 : array
    correct, on_estimates : bool
    Gx2, Gy2 : array
        ∂g/∂x (input, overwritten) and scratch.
    N2 : array
        Output.
    """
    C, E = P2.C, P2.E
    n, k, r = NX, NK, NY
    if on_estimates or not correct:
        dg_dy(v2, s, n + k + NP, s, n + k, Gy2)
        mm(Gy2, C, k, r, n, Gx2, 0, 0, 1)
    mm(E, Gx2, n, k, n, N2, 0, 0, 0)


def implicit_step(q: int, Phi1: Any, Phi2: Any, F: Any, Fd: Any, foh: bool, Nm: Any, s: Any,
                  so: int, out: Any, M: Any, rhs: Any) -> Any:
    """s⁺ = s + (I − γΦ₁N)⁻¹ (Φ₁F + Φ₂Ḟ) on the q entries at ``so`` (Ḟ only with ``foh``).

    The exponential, linearly implicit step of :mod:`~thetahat.estimation.observer.discretize`.

    Parameters
    ----------
    q : int
    Phi1, Phi2 : array
        h φ₁(hL), h² φ₂(hL).
    F, Fd : array
        Forcing and its rate over the step.
    foh : bool
    Nm : array
        State-dependent Jacobian part N.
    s, out : array
        Rows before and after the step.
    so : int
        Offset of the q entries in the rows.
    M, rhs : array
        Scratch.

    Returns
    -------
    int or array of int
        ``solve``'s status (per row in a batch): ``ST_OK``, or ``ST_SINGULAR`` when
        I − γΦ₁N is singular (``out`` is then not meaningful).
    """
    mv(Phi1, q, q, F, 0, rhs, 0, 0)
    if foh:
        mv(Phi2, q, q, Fd, 0, rhs, 0, 1)
    mm(Phi1, Nm, q, q, q, M, 0, 0, 0)
    eye_minus(M, q, IMPLICITNESS)
    status = solve(q, M, rhs)
    copy(q, s, so, out, so)
    axpy(q, 1.0, rhs, 0, out, so)
    return status


def second_step(P2: SecondArrays, s: Any, u0: Any, y0: Any, u1: Any, y1: Any, dt: float,
                correct: bool, foh: bool, on_estimates: bool, out: Any, W: tuple[Any, ...]
                ) -> Any:
    """x̂₂ of the second observer (Sec. VI) from ``s`` into ``out``, driven by θ̂ of ``s``.

    Parameters
    ----------
    P2 : tuple
        The second observer's plan arrays.
    s, out : array
        State rows before and after the step (only x̂₂ is written).
    u0, y0, u1, y1 : array
        Samples at the start and (``foh``) at the end of the step.
    dt : float
    correct, foh, on_estimates : bool
    W : tuple
        Work buffers (:data:`WORK`).

    Returns
    -------
    int or array of int
        The implicit step's status (:func:`implicit_step`).
    """
    v2, g2, Gx2, Gy2, F2, Fd2, N2, M2, rhs2, w2 = W[17:]
    n = NX
    second_forcing(P2, s, u0, y0, correct, on_estimates, v2, g2, Gx2, F2, w2)
    second_jacobian(P2, s, v2, correct, on_estimates, Gx2, Gy2, N2)
    if foh:
        second_forcing(P2, s, u1, y1, correct, on_estimates, v2, g2, Gx2, Fd2, w2)
        for i in range(n):
            put(Fd2, i, (get(Fd2, i) - get(F2, i)) / dt)
    return implicit_step(n, P2.Phi1, P2.Phi2, F2, Fd2, foh, N2, s, n + NK + NP, out, M2,
                         rhs2)


def phi_hat(g: Any, s: Any, phi: Any) -> None:
    """φ̂ = g(v, x̂, θ̂) + z (3c) into ``phi``, from g and the state rows ``s``.

    Parameters
    ----------
    g, s, phi : array
    """
    copy(NK, g, 0, phi, 0)
    axpy(NK, 1.0, s, NX, phi, 0)


def within_bound(s: Any, size: int) -> Any:
    """Rows whose norm is at most :data:`DIVERGENCE_BOUND` (False for NaN or inf).

    Parameters
    ----------
    s : array
    size : int

    Returns
    -------
    bool or array of bool
    """
    return sumsq(s, size) <= BOUND_SQ


def advance(P: PlanArrays, P2: SecondArrays, LP: LawArrays, s: Any, u0: Any,
            y0: Any, u1: Any, y1: Any, dt: float, correct: bool, foh: bool, second: bool,
            on_estimates: bool, out: Any, W: tuple[Any, ...]) -> int:
    """One step of the whole estimator from ``s`` into ``out``: (3a)–(3c), (8), Sec. VI.

    Over a missing sample (``correct`` False) the observers predict (y ← C x̂, no injection)
    and θ̂ and z are held.

    Parameters
    ----------
    P, P2 : tuple
        Plan arrays of the observer and of the second observer (module docstring).
    LP : tuple
        What ``law_step`` takes (the back end's).
    s : array
        State rows at the start of the step.
    u0, y0, u1, y1 : array
        Samples at the start and (``foh``) at the end of the step.
    dt : float
    correct, foh, second, on_estimates : bool
        The sample is present; first-order hold; a second observer is attached; its g sees
        C x̂₂.
    out : array
        State rows after the step.
    W : tuple
        Work buffers (:data:`WORK`).

    Returns
    -------
    int
        The status (module docstring).
    """
    v, g, Gx, Gy, Gth, F, Fd, Nm, M, rhs, phi, wr, wn, zc, dth, thn, lsn = W[:17]
    n, k, p = NX, NK, NP
    q = n + k
    observer_forcing(P, s, u0, y0, correct, v, g, Gx, F, wr, wn)
    phi_hat(g, s, phi)
    bad = False
    for a in range(k):
        bad = or_(bad, not_(isfinite(get(phi, a))))
    if any_(bad):
        return ST_DIVERGED
    copy(p, s, q, thn, 0)
    copy(LS, s, q + p + (n if second else 0), lsn, 0)
    fill(zc, 0.0)
    if correct:
        status = law_step(LP, v, s, 0, phi, s, q, dt, thn, lsn)
        if status != 0:
            return status
        moving = False
        for i in range(p):
            put(dth, i, get(thn, i) - get(s, q + i))
            moving = or_(moving, get(dth, i) != 0.0)
        if any_(moving):                            # skip ∂g/∂θ while θ̂ rests
            dg_dtheta(v, s, 0, s, q, Gth)
            mv(Gth, k, p, dth, 0, zc, 0, 0)
            for a in range(k):                      # −∂g/∂θ Δθ̂/dt: (3b)'s θ̂̇ term
                put(zc, a, where(moving, get(zc, a), 0.0) / -dt)
    observer_jacobian(P, s, v, correct, Gx, Gy, Nm)
    if foh:
        observer_forcing(P, s, u1, y1, correct, v, g, Gx, Fd, wr, wn)
        for i in range(q):
            put(Fd, i, (get(Fd, i) - get(F, i)) / dt)
    axpy(k, 1.0, zc, 0, F, n)
    if second:
        solved2 = second_step(P2, s, u0, y0, u1, y1, dt, correct, foh, on_estimates, out, W)
        if any_(solved2 != ST_OK):
            return ST_SINGULAR
    solved = implicit_step(q, P.Phi1, P.Phi2, F, Fd, foh, Nm, s, 0, out, M, rhs)
    if any_(solved != ST_OK):
        return ST_SINGULAR
    copy(p, thn, 0, out, q)
    copy(LS, lsn, 0, out, q + p + (n if second else 0))
    return ST_OK


#: The formulas a back end binds, by name.
FORMULAS: dict[str, Callable[..., Any]] = {
    "observer_forcing": observer_forcing, "observer_jacobian": observer_jacobian,
    "second_forcing": second_forcing, "second_jacobian": second_jacobian,
    "implicit_step": implicit_step, "second_step": second_step, "phi_hat": phi_hat,
    "within_bound": within_bound,
    "advance": advance}
