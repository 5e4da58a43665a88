"""The scalar side of the vocabulary (one row), and the compiled observer's loop.

The formulas printed for the ``"scalar"`` target (:mod:`~thetahat.estimation.kernels.subset`)
write most of the vocabulary of :mod:`~thetahat.estimation.kernels.primitives` as syntax and
their blocks as loops; what stays a call is defined here, in plain Python in the subset numba
compiles: the pivoted elimination ``solve``, the Taylor ``expm``, an ``exp`` without libm's
slow underflow path, ``isnan``, ``norm`` and ``sumsq`` (the length first). The module also
holds the compiled path's loop (:func:`kernel_run`), which calls the formulas'
:func:`~thetahat.estimation.observer.formulas.advance`. The numba module of
:mod:`~thetahat.estimation.observer.kernel_source` and the C of :mod:`thetahat.codegen` are
printed from these definitions.

Without numba these functions run as they are (slowly): the tests compare them with the
NumPy side one by one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..status import Status

if TYPE_CHECKING:                    # the argument tuples (named; every binding builds them)
    from .kernel_args import LawArrays, PlanArrays, SecondArrays, WorkArrays

__all__ = ["EXP_TINY_ARG", "SCALAR_PRIMITIVES"]

#: Below this argument exp underflows to 0 in float64 (the largest a with exp(a) == 0 is just
#: under it); ``math.exp`` there takes libm's slow path, which the scalar ``exp`` avoids.
EXP_TINY_ARG = -745.1332191019411

#: The status codes the primitives return (:class:`~thetahat.estimation.status.Status`; the
#: emitted module defines them from the same enum).
ST_OK = int(Status.OK)
ST_DIVERGED = int(Status.DIVERGED)
ST_SINGULAR = int(Status.SINGULAR)

# Names of the emitted module (declared for the type checker; never assigned here).
advance: Callable[..., int]
within_bound: Callable[..., bool]
readout: Callable[..., None]
NX: int
NU: int
NY: int
NK: int


def solve(q: int, M: Any, rhs: Any) -> int:
    # Gaussian elimination with partial pivoting; M is overwritten by its LU factors.
    # ST_SINGULAR at a zero pivot (LAPACK's info > 0), rhs then undefined; else ST_OK
    for c in range(q):
        piv = c
        best = abs(M[c, c])
        for i in range(c + 1, q):
            if abs(M[i, c]) > best:
                best = abs(M[i, c])
                piv = i
        if best == 0.0:
            return ST_SINGULAR
        if piv != c:
            for j in range(q):
                t = M[c, j]
                M[c, j] = M[piv, j]
                M[piv, j] = t
            t = rhs[c]
            rhs[c] = rhs[piv]
            rhs[piv] = t
        for i in range(c + 1, q):
            f = M[i, c] / M[c, c]
            for j in range(c + 1, q):
                M[i, j] -= f * M[c, j]
            rhs[i] -= f * rhs[c]
    for c in range(q - 1, -1, -1):
        t = rhs[c]
        for j in range(c + 1, q):
            t -= M[c, j] * rhs[j]
        rhs[c] = t / M[c, c]
    return ST_OK


def expm(q: int, Z: Any, E: Any, T: Any, U: Any) -> None:
    # Taylor series of degree 20 after scaling ||Z||_1 below 1/2, then squaring
    nrm = 0.0
    for j in range(q):
        acc = 0.0
        for i in range(q):
            acc += abs(Z[i, j])
        nrm = max(nrm, acc)
    squarings = 0
    scale = 1.0
    while nrm * scale > 0.5 and squarings < 1100:
        scale *= 0.5
        squarings += 1
    for i in range(q):
        for j in range(q):
            T[i, j] = 1.0 if i == j else 0.0
            E[i, j] = T[i, j]
    for deg in range(1, 21):
        for i in range(q):
            for j in range(q):
                acc = 0.0
                for l in range(q):  # noqa: E741
                    acc += T[i, l] * Z[l, j]
                U[i, j] = acc * scale / deg
        for i in range(q):
            for j in range(q):
                T[i, j] = U[i, j]
                E[i, j] += U[i, j]
    for _ in range(squarings):
        for i in range(q):
            for j in range(q):
                acc = 0.0
                for l in range(q):  # noqa: E741
                    acc += E[i, l] * E[l, j]
                U[i, j] = acc
        for i in range(q):
            for j in range(q):
                E[i, j] = U[i, j]


def exp(a: float) -> float:
    # math.exp, without libm's slow underflow path (errno) below EXP_TINY_ARG: the clamp is
    # branch-free, so the compiled code never calls exp with an underflowing argument
    e = math.exp(max(a, EXP_TINY_ARG))
    if a >= EXP_TINY_ARG:
        return e
    return 0.0 if a < EXP_TINY_ARG else a       # NaN stays NaN


def norm(n: int, a: Any) -> float:
    big = 0.0
    for i in range(n):
        big = max(big, abs(a[i]))
    safe = big if big > 0.0 else 1.0
    t = 0.0
    for i in range(n):
        t += (a[i] / safe) ** 2
    return big * math.sqrt(t)


def isnan(a: float) -> bool:
    return a != a


def sumsq(n: int, a: Any) -> float:
    t = 0.0
    for i in range(n):
        t += a[i] * a[i]
    return t


#: The scalar functions of the vocabulary, by name.
SCALAR_PRIMITIVES: dict[str, Callable[..., Any]] = {
    fn.__name__: fn for fn in (solve, expm, exp, isnan, norm, sumsq)}


def load_phis(PH: tuple[Any, ...], j: int, P: PlanArrays, P2: SecondArrays,
              second: bool) -> None:
    """Φ₁, Φ₂ of the observer (and of the second observer) of table entry ``j`` into P, P2."""
    Phi1, Phi2, Phi1s, Phi2s = PH[0], PH[1], PH[2], PH[3]
    for a in range(NX + NK):
        for b in range(NX + NK):
            P.Phi1[a, b] = Phi1[j, a, b]
            P.Phi2[a, b] = Phi2[j, a, b]
    if second:
        for a in range(NX):
            for b in range(NX):
                P2.Phi1[a, b] = Phi1s[j, a, b]
                P2.Phi2[a, b] = Phi2s[j, a, b]


def kernel_run(s0: Any, U: Any, Y: Any, dts: Any, ok: Any, plan_of: Any, PH: tuple[Any, ...],
               P: PlanArrays, P2: SecondArrays, LP: LawArrays, second: bool,
               on_estimates: bool, foh: bool, W: WorkArrays, rows: tuple[Any, ...], S: Any,
               PHI: Any) -> tuple[int, int]:
    """The states S and φ̂ = g + z (PHI) over a record; (status, failing step).

    Step i has length ``dts[i]``, its sample is present where ``ok[i]`` (else the observers
    predict over it), and its φ-matrices are entry ``plan_of[i]`` of the table ``PH`` =
    (Φ₁, Φ₂, Φ₁ of the second observer, Φ₂ of the second observer), each of shape (J, ·, ·),
    copied into P and P2 when the entry changes. ``foh``: first-order hold (the samples at
    the end of the step, y held over a missing one). ``rows`` holds buffers
    (s, s⁺, u, y, u₁, y₁) of one sample.
    """
    N, size = S.shape
    s, out, u, y, u1, y1 = rows
    for j in range(size):
        s[j] = s0[j]
        S[0, j] = s0[j]
    current = -1
    for i in range(N - 1):
        if plan_of[i] != current:
            current = plan_of[i]
            load_phis(PH, current, P, P2, second)
        correct = ok[i]
        end = i + 1 if foh else i
        held = end if (correct and ok[end]) else i
        for j in range(NU):
            u[j] = U[i, j]
            u1[j] = U[end, j]
        for j in range(NY):
            y[j] = Y[i, j]
            y1[j] = Y[held, j]
        status = advance(P, P2, LP, s, u, y, u1, y1, dts[i], correct, foh, second,
                         on_estimates, out, W)
        for a in range(NK):
            PHI[i, a] = W.phi[a]
        if status != 0:
            return status, i
        if not within_bound(out, size):
            return ST_DIVERGED, i
        for j in range(size):
            S[i + 1, j] = out[j]
        s, out = out, s
    for j in range(NU):
        u[j] = U[N - 1, j]
    for j in range(NY):
        y[j] = Y[N - 1, j]
    readout(P.C, s, u, y, ok[N - 1], W.v, W.g, W.phi)     # y ← C x̂ if the last is missing
    for a in range(NK):
        PHI[N - 1, a] = W.phi[a]
    return 0, 0
