"""One sample of observer (3), update law (8) and the second observer of Sec. VI: the definition.

The functions here are the step's formulas, written once in the formulas' language
(:mod:`~thetahat.estimation.kernels.subset`): named blocks of the state and of the work
buffers (x̂ = ``s[0:NX]``, z, θ̂, the u and y parts of v), the plan's matrices by name
(``P.A``, ``P.E``, ``P.K_x``, …) and block statements that read like the paper's equations
(``F_x[:] = P.A @ x_hat + P.B @ u + P.E @ g + P.E @ z``). They hold no data and import nothing
they call. Every back end is printed from them (:class:`~thetahat.estimation.kernels.printer.Program`):

* the Python step and run (one row) and :func:`~thetahat.estimation.observer.batch_run.run_batch`
  (B rows) run them printed for NumPy (:func:`~thetahat.estimation.observer.step.advance`);
* the compiled observer runs them printed as scalar loops, with the model functions printed
  from SymPy, in one numba module (:mod:`~thetahat.estimation.observer.kernel_source`,
  :mod:`~thetahat.estimation.observer.compiled`);
* :func:`thetahat.codegen.generate_c` prints the same scalar loops as C.

Free names a binding provides:

* the model functions ``g_dx(v, x, th, g, Gx)`` (g and ∂g/∂x at v, x̂ = ``x``, θ̂ = ``th``),
  ``g_val(v, x, th, g)``, ``dg_dy(v, x, th, Gy)`` (the y columns of ∂g/∂v) and
  ``dg_dtheta(v, x, th, Gth)``;
* ``law_step(LP, v, x, phi, th, dt, thn, lsn)``: the update law's step into θ̂⁺ (``thn``) and
  the law state (``lsn``, which holds the state at the start on entry); it returns 0, or
  ``ST_THETA_STAR`` where θ* is invalid under ``on_invalid='raise'``
  (:mod:`~thetahat.estimation.observer.laws.formulas`);
* the dimensions ``NX, NU, NY, NK, NP``, ``NV`` = NU + NY, ``NQ`` = NX + NK and ``LS`` (law
  state length), the implicitness γ ``IMPLICITNESS``, the divergence bound ``BOUND_SQ``
  (:data:`DIVERGENCE_BOUND` squared) and the status codes ``ST_<NAME>`` of
  :class:`~thetahat.estimation.status.Status`.

The state of a row is ``s = col(x̂, z, θ̂[, x̂₂][, law state])``. The tuples of
:mod:`~thetahat.estimation.kernels.kernel_args`: ``P`` (the observer's plan arrays with the
φ-matrices of this step: corrected, or the prediction's over a missing sample), ``P2`` (the
second observer's), ``LP`` (the law's) and the work buffers ``W``.

Status codes of :func:`advance` (:class:`~thetahat.estimation.status.Status`): ``ST_OK``;
``ST_DIVERGED`` when φ̂ is not finite; ``ST_THETA_STAR`` when θ* is invalid (the law's);
``ST_SINGULAR`` when an implicit step's matrix is singular (``solve``'s status).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                    # the argument tuples (named; every binding builds them)
    from ..kernels.kernel_args import LawArrays, PlanArrays, SecondArrays, WorkArrays

__all__ = ["CALLS", "DIVERGENCE_BOUND", "FORMULAS", "VIEWED", "advance", "implicit_step", "observer_forcing",
           "observer_jacobian", "phi_hat", "readout", "second_forcing", "second_jacobian",
           "second_step", "within_bound"]

#: A row of the state has diverged when its Euclidean norm exceeds this (or is not finite).
#: No observer quantity of a sensibly scaled problem comes near it, and its square (1e200)
#: stays finite, so one dot product per step decides. The same rule in every back end makes
#: them report a divergence at the same sample.
DIVERGENCE_BOUND = 1e100

#: The functions the formulas call that a binding provides, with their parameters
#: (module docstring).
CALLS = {"g_dx": ("v", "x", "th", "g", "Gx"), "g_val": ("v", "x", "th", "g"),
         "dg_dy": ("v", "x", "th", "Gy"), "dg_dtheta": ("v", "x", "th", "Gth"),
         "law_step": ("LP", "v", "x", "phi", "th", "dt", "thn", "lsn")}
#: The parameters of those functions (and of the laws' hooks) that take a view of the state:
#: x̂ and θ̂ (an array and an offset in the scalar code).
VIEWED = frozenset({"x", "th"})

# Names bound by a back end (declared for the type checker; never assigned here).
Prim = Callable[..., Any]
eye: Prim
solve: Prim
where: Prim
isfinite: Prim
not_: Prim
or_: Prim
any_: Prim
sumsq: Prim
g_dx: Prim
g_val: Prim
dg_dy: Prim
dg_dtheta: Prim
law_step: Prim
NX: int
NU: int
NY: int
NK: int
NP: int
NV: int
NQ: int
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
    P : PlanArrays
        The observer's plan arrays.
    s : array
        A state row.
    u : array, shape (NU,)
    y : array, shape (NY,)
        The samples.
    correct : bool
        The sample y is present.
    v : array, shape (NV,)
        Output: v = col(u, y).
    g : array, shape (NK,)
        Output: g(v, x̂, θ̂).
    Gx : array, shape (NK, NX)
        Output: ∂g/∂x.
    F : array, shape (NQ,)
        Output: the forcing.
    wr : array, shape (NY,)
        Scratch: ỹ.
    wn : array, shape (NX,)
        Scratch: K_x ỹ.
    """
    x_hat, z, theta_hat, xz = s[0:NX], s[NX:NX + NK], s[NQ:NQ + NP], s[0:NQ]
    v_u, v_y = v[0:NU], v[NU:NU + NY]
    F_x, F_z = F[0:NX], F[NX:NX + NK]
    v_u[:] = u
    if correct:
        v_y[:] = y
    else:
        v_y[:] = P.C @ x_hat                                 # y ← C x̂
    g_dx(v, x_hat, theta_hat, g, Gx)
    if correct:
        F[:] = P.L @ xz + P.Bv @ v
        F_x += P.E @ g
        wr[:] = v_y - P.C @ x_hat                            # ỹ = y − C x̂
        wn[:] = P.K_x @ wr
        F_z -= Gx @ wn                                       # − ∂g/∂x K_x ỹ
    else:
        F_x[:] = P.A @ x_hat + P.B @ u + P.E @ g + P.E @ z   # A x̂ + B u + E (g + z)
        F_z[:] = 0.0


def observer_jacobian(P: PlanArrays, s: Any, v: Any, correct: bool, Gx: Any, Gy: Any,
                      Nm: Any) -> None:
    """N = [[E ∂g/∂x, 0], [∂g/∂x K_x C, 0]] (measured) or [[E(∂g/∂x + ∂g/∂y C), 0], [0, 0]].

    The linearisation ∂d/∂(x̂, φ̂) of the paper's d without the terms proportional to ỹ and
    θ̂̇. Over a missing sample ``Gx`` is overwritten by ∂g/∂x + ∂g/∂y C.

    Parameters
    ----------
    P : PlanArrays
    s : array
        A state row.
    v : array, shape (NV,)
        The v of :func:`observer_forcing`.
    correct : bool
    Gx : array, shape (NK, NX)
        ∂g/∂x (input).
    Gy : array, shape (NK, NY)
        Scratch for ∂g/∂y.
    Nm : array, shape (NQ, NQ)
        Output: N.
    """
    x_hat, theta_hat = s[0:NX], s[NQ:NQ + NP]
    Nm[:] = 0.0
    if correct:
        Nm[0:NX, 0:NX] = P.E @ Gx
        Nm[NX:NX + NK, 0:NX] = Gx @ P.KxC
    else:
        dg_dy(v, x_hat, theta_hat, Gy)
        Gx += Gy @ P.C
        Nm[0:NX, 0:NX] = P.E @ Gx


def second_forcing(P2: SecondArrays, s: Any, u: Any, y: Any, correct: bool,
                   on_estimates: bool, v2: Any, g2: Any, Gx2: Any, F2: Any, w2: Any) -> None:
    """F = A x̂₂ + B u + E g(v̄, x̂₂, θ̂) + K_x2 (y − C x̂₂) of Sec. VI; v̄, g, ∂g/∂x into buffers.

    v̄ = col(u, C x̂₂) with ``on_estimates`` (the plan's ``g_on_estimates``) or over a missing
    sample (no injection then), else col(u, y); θ̂ is the one at the start of the step.

    Parameters
    ----------
    P2 : SecondArrays
        The second observer's plan arrays.
    s : array
        A state row (x̂₂ after θ̂).
    u : array, shape (NU,)
    y : array, shape (NY,)
    correct, on_estimates : bool
    v2 : array, shape (NV,)
        Output: v̄.
    g2 : array, shape (NK,)
        Output: g(v̄, x̂₂, θ̂).
    Gx2 : array, shape (NK, NX)
        Output: ∂g/∂x.
    F2 : array, shape (NX,)
        Output: F.
    w2 : array, shape (NY,)
        Scratch: y − C x̂₂.
    """
    theta_hat, x2 = s[NQ:NQ + NP], s[NQ + NP:NQ + NP + NX]
    v_u, v_y = v2[0:NU], v2[NU:NU + NY]
    v_u[:] = u
    if on_estimates or not correct:
        v_y[:] = P2.C @ x2
    else:
        v_y[:] = y
    g_dx(v2, x2, theta_hat, g2, Gx2)
    F2[:] = P2.A @ x2 + P2.B @ u + P2.E @ g2
    if correct:
        w2[:] = y - P2.C @ x2
        F2 += P2.K_x @ w2


def second_jacobian(P2: SecondArrays, s: Any, v2: Any, correct: bool, on_estimates: bool,
                    Gx2: Any, Gy2: Any, N2: Any) -> None:
    """N = E ∂g/∂x, plus E ∂g/∂y C where g sees C x̂₂ (the exact Jacobian of F in x̂₂).

    Parameters
    ----------
    P2 : SecondArrays
    s : array
        A state row.
    v2 : array, shape (NV,)
    correct, on_estimates : bool
    Gx2 : array, shape (NK, NX)
        ∂g/∂x (input, overwritten).
    Gy2 : array, shape (NK, NY)
        Scratch.
    N2 : array, shape (NX, NX)
        Output.
    """
    theta_hat, x2 = s[NQ:NQ + NP], s[NQ + NP:NQ + NP + NX]
    if on_estimates or not correct:
        dg_dy(v2, x2, theta_hat, Gy2)
        Gx2 += Gy2 @ P2.C
    N2[:] = P2.E @ Gx2


def implicit_step(q: int, Phi1: Any, Phi2: Any, F: Any, Fd: Any, foh: bool, Nm: Any, s: Any,
                  out: Any, M: Any, rhs: Any) -> Any:
    """s⁺ = s + (I − γΦ₁N)⁻¹ (Φ₁F + Φ₂Ḟ) on a block of q entries (Ḟ only with ``foh``).

    The exponential, linearly implicit step of :mod:`~thetahat.estimation.observer.discretize`.

    Parameters
    ----------
    q : int
    Phi1, Phi2 : array, shape (q, q)
        h φ₁(hL), h² φ₂(hL).
    F, Fd : array, shape (q,)
        Forcing and its rate over the step.
    foh : bool
    Nm : array, shape (q, q)
        State-dependent Jacobian part N.
    s, out : array, shape (q,)
        The block before and after the step.
    M : array, shape (q, q)
        Scratch.
    rhs : array, shape (q,)
        Scratch.

    Returns
    -------
    int or array of int
        ``solve``'s status (per row in a batch): ``ST_OK``, or ``ST_SINGULAR`` when
        I − γΦ₁N is singular (``out`` is then not meaningful).
    """
    rhs[:] = Phi1 @ F
    if foh:
        rhs += Phi2 @ Fd
    M[:] = eye(q) - IMPLICITNESS * (Phi1 @ Nm)
    status = solve(M, rhs)
    out[:] = s + rhs
    return status


def second_step(P2: SecondArrays, s: Any, u0: Any, y0: Any, u1: Any, y1: Any, dt: float,
                correct: bool, foh: bool, on_estimates: bool, out: Any, W: WorkArrays
                ) -> Any:
    """x̂₂ of the second observer (Sec. VI) from ``s`` into ``out``, driven by θ̂ of ``s``.

    Parameters
    ----------
    P2 : SecondArrays
        The second observer's plan arrays.
    s, out : array
        State rows before and after the step (only x̂₂ is written).
    u0, y0, u1, y1 : array
        Samples at the start and (``foh``) at the end of the step.
    dt : float
    correct, foh, on_estimates : bool
    W : WorkArrays
        Work buffers.

    Returns
    -------
    int or array of int
        The implicit step's status (:func:`implicit_step`).
    """
    x2, x2_next = s[NQ + NP:NQ + NP + NX], out[NQ + NP:NQ + NP + NX]
    second_forcing(P2, s, u0, y0, correct, on_estimates, W.v2, W.g2, W.Gx2, W.F2, W.w2)
    second_jacobian(P2, s, W.v2, correct, on_estimates, W.Gx2, W.Gy2, W.N2)
    if foh:
        second_forcing(P2, s, u1, y1, correct, on_estimates, W.v2, W.g2, W.Gx2, W.Fd2, W.w2)
        W.Fd2[:] = (W.Fd2 - W.F2) / dt
    return implicit_step(NX, P2.Phi1, P2.Phi2, W.F2, W.Fd2, foh, W.N2, x2, x2_next, W.M2,
                         W.rhs2)


def phi_hat(g: Any, s: Any, phi: Any) -> None:
    """φ̂ = g(v, x̂, θ̂) + z (3c) into ``phi``, from g and the state row ``s``.

    Parameters
    ----------
    g : array, shape (NK,)
    s : array
        A state row.
    phi : array, shape (NK,)
        Output.
    """
    phi[:] = g + s[NX:NX + NK]


def readout(C: Any, s: Any, u: Any, y: Any, correct: bool, v: Any, g: Any, phi: Any) -> None:
    """φ̂ = g(v, x̂, θ̂) + z at a sample, v = col(u, y), or col(u, C x̂) when y is missing.

    What a run records at its last sample (the compiled loop) and the C API's
    ``<name>_phi_hat``.

    Parameters
    ----------
    C : array, shape (NY, NX)
        C of (1).
    s : array
        The state row.
    u : array, shape (NU,)
    y : array, shape (NY,)
        The samples.
    correct : bool
        y is present.
    v : array, shape (NV,)
        Scratch: v.
    g : array, shape (NK,)
        Scratch: g.
    phi : array, shape (NK,)
        Output: φ̂.
    """
    x_hat, theta_hat = s[0:NX], s[NQ:NQ + NP]
    v_u, v_y = v[0:NU], v[NU:NU + NY]
    v_u[:] = u
    if correct:
        v_y[:] = y
    else:
        v_y[:] = C @ x_hat
    g_val(v, x_hat, theta_hat, g)
    phi_hat(g, s, phi)


def within_bound(s: Any, size: int) -> Any:
    """Rows whose norm is at most :data:`DIVERGENCE_BOUND` (False for NaN or inf).

    Parameters
    ----------
    s : array, shape (size,)
    size : int

    Returns
    -------
    bool or array of bool
    """
    return sumsq(s) <= BOUND_SQ


def advance(P: PlanArrays, P2: SecondArrays, LP: LawArrays, s: Any, u0: Any,
            y0: Any, u1: Any, y1: Any, dt: float, correct: bool, foh: bool, second: bool,
            on_estimates: bool, out: Any, W: WorkArrays) -> int:
    """One step of the whole estimator from ``s`` into ``out``: (3a)–(3c), (8), Sec. VI.

    Over a missing sample (``correct`` False) the observers predict (y ← C x̂, no injection)
    and θ̂ and z are held.

    Parameters
    ----------
    P : PlanArrays
    P2 : SecondArrays
        Plan arrays of the observer and of the second observer (module docstring).
    LP : LawArrays
        What ``law_step`` takes (the back end's).
    s : array
        State row at the start of the step.
    u0, y0, u1, y1 : array
        Samples at the start and (``foh``) at the end of the step.
    dt : float
    correct, foh, second, on_estimates : bool
        The sample is present; first-order hold; a second observer is attached; its g sees
        C x̂₂.
    out : array
        State row after the step.
    W : WorkArrays
        Work buffers.

    Returns
    -------
    int
        The status (module docstring).
    """
    x_hat, theta_hat, xz = s[0:NX], s[NQ:NQ + NP], s[0:NQ]
    xz_next, theta_next = out[0:NQ], out[NQ:NQ + NP]
    at = NQ + NP + (NX if second else 0)                     # where the law state starts
    law_state, law_next = s[at:at + LS], out[at:at + LS]
    F, Fd, phi, thn, dth, zc = W.F, W.Fd, W.phi, W.thn, W.dth, W.zc
    observer_forcing(P, s, u0, y0, correct, W.v, W.g, W.Gx, F, W.wr, W.wn)
    phi_hat(W.g, s, phi)
    bad = False
    for a in range(NK):
        bad = or_(bad, not_(isfinite(phi[a])))
    if any_(bad):
        return ST_DIVERGED
    thn[:] = theta_hat
    W.lsn[0:LS] = law_state
    zc[:] = 0.0
    if correct:
        status = law_step(LP, W.v, x_hat, phi, theta_hat, dt, thn, W.lsn)
        if status != 0:
            return status
        moving = False
        for i in range(NP):
            dth[i] = thn[i] - theta_hat[i]
            moving = or_(moving, dth[i] != 0.0)
        if any_(moving):                                     # skip ∂g/∂θ while θ̂ rests
            dg_dtheta(W.v, x_hat, theta_hat, W.Gth)
            zc[:] = W.Gth @ dth
            for a in range(NK):                              # −∂g/∂θ Δθ̂/dt: (3b)'s θ̂̇ term
                zc[a] = where(moving, zc[a], 0.0) / -dt
    observer_jacobian(P, s, W.v, correct, W.Gx, W.Gy, W.Nm)
    if foh:
        observer_forcing(P, s, u1, y1, correct, W.v, W.g, W.Gx, Fd, W.wr, W.wn)
        Fd[:] = (Fd - F) / dt
    F_z = F[NX:NX + NK]
    F_z += zc
    if second:
        solved2 = second_step(P2, s, u0, y0, u1, y1, dt, correct, foh, on_estimates, out, W)
        if any_(solved2 != ST_OK):
            return ST_SINGULAR
    solved = implicit_step(NQ, P.Phi1, P.Phi2, F, Fd, foh, W.Nm, xz, xz_next, W.M, W.rhs)
    if any_(solved != ST_OK):
        return ST_SINGULAR
    theta_next[:] = thn
    law_next[:] = W.lsn[0:LS]
    return ST_OK


#: The formulas a back end prints, by name.
FORMULAS: dict[str, Callable[..., Any]] = {
    "observer_forcing": observer_forcing, "observer_jacobian": observer_jacobian,
    "second_forcing": second_forcing, "second_jacobian": second_jacobian,
    "implicit_step": implicit_step, "second_step": second_step, "phi_hat": phi_hat,
    "readout": readout, "within_bound": within_bound, "advance": advance}
