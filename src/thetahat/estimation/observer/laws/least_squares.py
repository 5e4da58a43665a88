r"""The least-squares law on the filtered regressor: θ̂ from the observer's own residual, the
regressor passed through the same filter as φ̂, with a gain that shrinks as information grows.

The gradient law of Propositions 3–4 correlates the residual z = φ̂ − g(v, x̂, θ̂) with the
regressor J = ∂g/∂θ(v, x̂, θ̂). But φ̂ is the perturbation seen through the observer: to first
order in θ̃ = θ − θ̂ (θ̂ held), z is the mismatch φ − g passed through the filter of the
observer's error dynamics (the map φ → φ̂ of (3) with g known),

    F(s) = −H L (sI − L)⁻¹ G,   L = [[A − K_x C, E], [−K_φ C, 0]],  G = col(0, I_k),
    H = [0, I_k],   F(0) = I,

so that z ≈ F[J] θ̃, while J itself is not filtered. When J varies within the observer's
bandwidth (a Coulomb switch at each reversal, an acceleration), Σ Jᵀz = 0 is not at θ̃ = 0:
the rest point of the gradient law is biased by the observer's lag, even on exact data.
:func:`error_filter` gives F's realisation; :class:`FilteredLeastSquares` regresses z on
W = F[J], the like-for-like regressor, and weighs the whole record as a least squares:

    Γ(t)⁻¹ = Γ₀⁻¹ + ∫₀ᵗ WᵀW,   θ̂̇ = Proj(Γ(t) Wᵀ z).

This is the recursive least squares of adaptive control (Ioannou & Sun 1996, Sec. 4.3.6)
with the filtered regressor of the swapping lemma (ibid., Sec. 4.3.7); it is not one of the
paper's Propositions, whose laws use J itself: see the class's notes for what carries over.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import final

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...._validate import positive_scalar
from ....errors import DimensionError, UpdateLawError
from ....model.jacobian_check import require_theta_dependence
from ....model.paramset import Box, ParameterSet
from ....model.perturbation import Perturbation
from ....model.system import PerturbedLinearSystem
from ..discretize import PlanCache
from ...kernels.kernel_args import LawArrays
from ...status import status_constants
from .base import FAR, UpdateLaw, as_batch, broadcast_rows, law_binding
from .projection import as_gain

__all__ = ["ErrorFilter", "FilteredLeastSquares", "error_filter"]

FloatArray = NDArray[np.float64]


@final
@dataclass(frozen=True, slots=True, eq=False)
class ErrorFilter:
    """The observer's map φ → φ̂: ẇ = L w + G φ, φ̂ = H w (:func:`error_filter`).

    Parameters
    ----------
    L : ndarray, shape (n + k, n + k)
        The error dynamics [[A − K_x C, E], [−K_φ C, 0]] (Hurwitz for a stable design).
    G : ndarray, shape (n + k, k)
        col(0, I_k): where φ enters.
    H : ndarray, shape (k, n + k)
        The readout −[0, I_k] L = [K_φ C, 0], so that F(0) = I.
    """

    L: FloatArray
    G: FloatArray
    H: FloatArray
    _plans: PlanCache = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_plans", PlanCache(self.L))

    def transfer(self, s: complex) -> NDArray[np.complex128]:
        """F(s) = H (sI − L)⁻¹ G, shape (k, k).

        Parameters
        ----------
        s : complex

        Returns
        -------
        ndarray, shape (k, k)
        """
        nk = self.L.shape[0]
        return self.H @ np.linalg.solve(s * np.eye(nk) - self.L, self.G.astype(complex))

    def discrete_phi1(self, dt: float) -> FloatArray:
        """Φ₁ = ∫₀^dt e^{Ls} ds = dt φ₁(dt L), shape (n + k, n + k) (the observer's cached
        φ-function of the same L).

        Parameters
        ----------
        dt : float
            Step length > 0.

        Returns
        -------
        ndarray, shape (n + k, n + k)
        """
        return self._plans.get(positive_scalar("dt", dt)).Phi1

    def discrete(self, dt: float) -> tuple[FloatArray, FloatArray]:
        """(e^{L dt}, ∫₀^dt e^{Ls} ds G): the exact step with the input held over dt.

        From the observer's cached φ-functions (:class:`~thetahat.estimation.observer.discretize.PlanCache`):
        ∫₀^dt e^{Ls} ds = dt φ₁(dt L) = Φ₁ and e^{L dt} = I + L Φ₁.

        Parameters
        ----------
        dt : float
            Step length > 0.

        Returns
        -------
        Ad : ndarray, shape (n + k, n + k)
        Bd : ndarray, shape (n + k, k)
        """
        Phi1 = self.discrete_phi1(dt)
        return np.eye(self.L.shape[0]) + self.L @ Phi1, Phi1 @ self.G


def error_filter(system: PerturbedLinearSystem, K_x: ArrayLike, K_phi: ArrayLike
                 ) -> ErrorFilter:
    """The filter F(s) through which the observer (3) with gains (K_x, K_φ) sees φ.

    With g known and θ̂ held (z carries the change of g along x̂), the errors obey
    x̃̇ = (A − K_x C) x̃ + E(φ − φ̂) and φ̂̇ = K_φ C x̃; with w = col(∫x̃, ∫(φ − φ̂)) this is
    ẇ = L w + G φ, φ̂ = H w, the matrices of :class:`ErrorFilter`: φ̂ follows φ through
    F(s) = H (sI − L)⁻¹ G. F(0) = I: a constant φ is recovered exactly.

    Parameters
    ----------
    system : PerturbedLinearSystem
        (A, C, E) of the plant.
    K_x : array_like, shape (n, r)
    K_phi : array_like, shape (k, r)
        The observer's gains.

    Returns
    -------
    ErrorFilter

    Examples
    --------
    A double integrator with φ the acceleration, the EMPS model's linear part:

    >>> import numpy as np
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.estimation.observer.laws.least_squares import error_filter
    >>> s = PerturbedLinearSystem(A=[[0, 1], [0, 0]], B=[[0], [0]], C=[[1, 0]], E=[[0], [1]])
    >>> F = error_filter(s, [[120.0], [4400.0]], [[48000.0]])   # poles −20, −40, −60
    >>> np.round(F.transfer(0.0).real, 12).tolist()
    [[1.0]]
    >>> np.round(np.sort(np.linalg.eigvals(F.L).real), 6).tolist()
    [-60.0, -40.0, -20.0]
    """
    A, C, E = system.A, system.C, system.E
    n, k = A.shape[0], E.shape[1]
    Kx = np.asarray(K_x, dtype=np.float64).reshape(n, -1)
    Kphi = np.asarray(K_phi, dtype=np.float64).reshape(k, -1)
    L = np.block([[A - Kx @ C, E], [-Kphi @ C, np.zeros((k, k))]])
    G = np.vstack([np.zeros((n, k)), np.eye(k)])
    H = -G.T @ L
    return ErrorFilter(L=L, G=G, H=H)


@final
@dataclass(frozen=True, slots=True, eq=False)
class FilteredLeastSquares(UpdateLaw):
    r"""θ̂̇ = Proj(Γ(t) Wᵀ(φ̂ − g(v, x̂, θ̂))), d(Γ⁻¹)/dt = WᵀW, W = F[∂g/∂θ].

    $$
    \dot{\hat\theta} = \operatorname{Proj}\bigl(\Gamma W^\top(\hat\phi - g(v, \hat x,
      \hat\theta))\bigr), \qquad \frac{d}{dt}\Gamma^{-1} = W^\top W, \qquad
      W = F\Bigl[\frac{\partial g}{\partial\theta}(v, \hat x, \hat\theta)\Bigr]
    $$

    F is the observer's error filter (module doc): the law is bound to an observer's gains
    when the observer is built (:meth:`for_observer`, called by
    :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`).

    Parameters
    ----------
    perturbation : Perturbation
        g and ∂g/∂θ.
    Gamma : float or array_like, shape (p, p)
        Γ₀ = Γ(0), symmetric positive definite; Γ₀⁻¹ is the prior information on θ̂₀
        (``Gamma = "auto"`` in a model file: :mod:`~thetahat.estimation.observer.auto_gain`'s
        Γ₀ with the prior worth 1/κ of the record, κ = ``PRIOR_KAPPA``).
    parameter_set : ParameterSet
        Θ; its dimension must equal the perturbation's p.
    filter : ErrorFilter, optional
        F; None until the law is bound to an observer.

    Raises
    ------
    UpdateLawError
        Γ₀ not symmetric positive definite; g does not depend on θ.
    DimensionError
        Θ and the perturbation disagree on p; a filter of the wrong size.

    Notes
    -----
    **State.** col(w, R): the filter's state w ((n + k) × p, started at 0: W = 0 until data
    arrive) and the information R = Γ⁻¹ (p × p, started at Γ₀⁻¹), row-major, after θ̂ in the
    observer's state.

    **Step.** With J, z = φ̂ − g and W = H w held over dt, θ̂⁺ minimises
    ½(θ − θ̂)ᵀR(θ − θ̂) + ½dt‖z − W(θ − θ̂)‖²: R⁺ = R + dt WᵀW, θ̂⁺ = θ̂ + (R⁺)⁻¹dt Wᵀz (the
    formulas' ``solve``), then the R⁺-weighted projection onto Θ (``parameter_set.nearest`` with
    that metric), so θ̂ ∈ Θ at every step; w⁺ = e^{L dt} w + ∫e^{Ls}G ds J (exact for J held).
    R only gains positive semi-definite terms: it stays symmetric positive definite, and the
    step is stable for every dt. A sample whose J or z is not finite leaves θ̂ and R as they
    are (w decays as with J = 0).

    **What carries over from the paper.** The observer's error bounds need only θ̂ ∈ Θ
    (Assumption 3), which the projection keeps. Propositions 3–4 prove convergence of the
    law with J; for this one the standard argument holds on the filtered error model
    z = W θ̃ (g linear in θ, θ̂ slow): V = θ̃ᵀRθ̃ is non-increasing and θ̂ tends to the
    least-squares fit of z on W. With g nonlinear in θ, that fit is about the current θ̂: a
    local result, stated as such.

    **Back ends.** The step is written once,
    :func:`~thetahat.estimation.observer.laws.formulas.least_squares_law`: :meth:`advance` runs
    it printed for NumPy (the observer's ``step``, ``run`` and ``run_batch``; the projection
    by ``parameter_set.nearest``), and the numba kernel
    (:func:`~thetahat.estimation.observer.compiled.compile_observer`, chosen by the runner for
    ``run_estimator`` and ``thetahat estimate``) prints it as scalar loops with the state in
    the kernel's row, for a :class:`~thetahat.model.paramset.Box` Θ (its projection in R⁺'s
    metric: :func:`~thetahat.estimation.kernels.set_projection.project_box_metric`). A Ball,
    Ellipsoid or other Θ runs on the Python path (the kernel refuses it with
    :class:`~thetahat.errors.UnsupportedError`). The generated C does not carry it:
    ``generate_c`` refuses the law (a law with a state of its own), and the runner takes the
    numba kernel.

    Examples
    --------
    The filtered regressor makes z = W θ̃ exact for g linear in θ; here, a one-state plant
    whose φ = θ·u is estimated from y:

    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.estimation.observer.observer import ModifiedHighGainObserver
    >>> from thetahat.estimation.observer.laws.least_squares import FilteredLeastSquares
    >>> g = parse_perturbation("a*u", u=["u"], y=["y"], x=["x"], theta=["a"])
    >>> s = PerturbedLinearSystem(A=[[-1.0]], B=[[0.0]], C=[[1.0]], E=[[1.0]], perturbation=g)
    >>> law = FilteredLeastSquares(g, 1e4, Box([0.0], [5.0]))   # a weak prior on θ̂₀
    >>> obs = ModifiedHighGainObserver(system=s, K_x=[[20.0]], K_phi=[[100.0]], update_law=law)
    >>> t = np.arange(0.0, 10.0, 1e-3)
    >>> u = np.sin(3 * t)
    >>> y = (2.0 * (3 * np.exp(-t) + np.sin(3 * t) - 3 * np.cos(3 * t)) / 10)[:, None]
    >>> res = obs.run(t, u[:, None], y, state0=obs.init(theta_hat0=[1.0]))
    >>> round(float(res.theta_hat[-1, 0]), 3)     # the true a = 2 (Γ₀ = 1: 1.80, the prior)
    2.0
    """

    perturbation: Perturbation
    Gamma: FloatArray
    parameter_set: ParameterSet
    filter: ErrorFilter | None = None
    _R0: FloatArray = field(init=False, repr=False)

    def __init__(self, perturbation: Perturbation, Gamma: ArrayLike,
                 parameter_set: ParameterSet, *, filter: ErrorFilter | None = None) -> None:
        if not isinstance(parameter_set, ParameterSet):
            raise DimensionError(f"FilteredLeastSquares: parameter_set must be a thetahat "
                                 f"ParameterSet; got {type(parameter_set).__name__}.")
        if not isinstance(perturbation, Perturbation):
            raise DimensionError(f"perturbation must be a thetahat Perturbation; got "
                                 f"{type(perturbation).__name__}.")
        n, _, _, p, k = perturbation.dims
        if p != parameter_set.dim:
            raise DimensionError(f"parameter_set has dimension {parameter_set.dim} but the "
                                 f"perturbation has p = {p} parameters.")
        require_theta_dependence(perturbation, parameter_set, owner="FilteredLeastSquares")
        G0 = as_gain("Gamma", Gamma, p)
        if filter is not None and (not isinstance(filter, ErrorFilter)
                                   or filter.G.shape != (n + k, k)):
            raise DimensionError(f"FilteredLeastSquares: filter must be an ErrorFilter of "
                                 f"size n + k = {n + k} (error_filter(system, K_x, K_phi)).")
        object.__setattr__(self, "perturbation", perturbation)
        object.__setattr__(self, "Gamma", G0)
        object.__setattr__(self, "parameter_set", parameter_set)
        object.__setattr__(self, "filter", filter)
        R0 = np.linalg.inv(G0)
        object.__setattr__(self, "_R0", 0.5 * (R0 + R0.T))

    # ------------------------------------------------------------------ binding
    def for_observer(self, system: PerturbedLinearSystem, K_x: FloatArray,
                     K_phi: FloatArray) -> FilteredLeastSquares:
        """This law with F = the error filter of the observer with gains (K_x, K_φ).

        Parameters
        ----------
        system : PerturbedLinearSystem
        K_x : ndarray, shape (n, r)
        K_phi : ndarray, shape (k, r)

        Returns
        -------
        FilteredLeastSquares
        """
        return FilteredLeastSquares(self.perturbation, self.Gamma, self.parameter_set,
                                    filter=error_filter(system, K_x, K_phi))

    @property
    def gain(self) -> FloatArray | None:
        """None: Γ₀ enters the law's state (build one law per Γ₀), not a per-row gain."""
        return None

    @property
    def state_size(self) -> int:
        """(n + k)(p + 1) + k + p²: the filters of J and of Jθ̂ − a, a, the information R."""
        n, _, _, p, k = self.perturbation.dims
        return (n + k) * (p + 1) + k + p * p

    def _split(self, row: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(w (n + k, p), w_b (n + k,), a (k,), R (p, p)) of one state row (views)."""
        n, _, _, p, k = self.perturbation.dims
        nk, nw = n + k, (n + k) * p
        return (row[:nw].reshape(nk, p), row[nw:nw + nk], row[nw + nk:nw + nk + k],
                row[nw + nk + k:].reshape(p, p))

    def init_state(self, theta_hat0: FloatArray) -> FloatArray:
        """col(w = 0, R = Γ₀⁻¹), broadcast over θ̂₀'s leading shape.

        Parameters
        ----------
        theta_hat0 : ndarray, shape (..., p)

        Returns
        -------
        ndarray, shape (..., state_size)
        """
        th = np.asarray(theta_hat0, dtype=np.float64)
        n, _, _, p, k = self.perturbation.dims
        one = np.concatenate([np.zeros((n + k) * (p + 1) + k), self._R0.ravel()])
        return np.broadcast_to(one, th.shape[:-1] + one.shape).copy()

    # ------------------------------------------------------------------ law
    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """Refused: the law's gain and regressor are its state, defined by its step only.

        Raises
        ------
        UpdateLawError
            Always; use the observer's ``step`` or ``run``.
        """
        raise UpdateLawError("FilteredLeastSquares carries a state (the filtered regressor "
                             "and Γ(t)⁻¹): it has no memoryless rate; run it through the "
                             "observer's step or run.")

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """Refused for the same reason as :meth:`rate`: use :meth:`advance` with the state.

        Raises
        ------
        UpdateLawError
            Always.
        """
        raise UpdateLawError("FilteredLeastSquares carries a state: call advance(v, x_hat, "
                             "phi_hat, theta_hat, state, dt), or run it through the "
                             "observer's step or run.")

    def advance(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
                theta_hat: FloatArray, state: FloatArray, dt: float, *,
                Gamma: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
        """One step of θ̂ and of col(w, R) (class notes); θ̂ in Θ.

        Parameters
        ----------
        v, x_hat, phi_hat, theta_hat : ndarray, shapes (B, m + r), (B, n), (B, k), (B, p)
        state : ndarray, shape (B, state_size)
        dt : float
            Step length > 0.
        Gamma : None
            Refused: Γ₀ is part of the state.

        Returns
        -------
        theta_hat : ndarray, shape (B, p)
        state : ndarray, shape (B, state_size)

        Raises
        ------
        UpdateLawError
            The law is not bound to an observer, or a per-row Γ is given.
        """
        if self.filter is None:
            raise UpdateLawError("FilteredLeastSquares is not bound to an observer: build the "
                                 "observer with it (ModifiedHighGainObserver binds it to its "
                                 "gains), or call for_observer(system, K_x, K_phi).")
        if Gamma is not None:
            raise UpdateLawError("FilteredLeastSquares: Γ₀ is part of the law's state; build "
                                 "one law per Γ₀ instead of passing Gamma per row.")
        dt = positive_scalar("dt", dt)
        n, _, _, p, k = self.perturbation.dims
        v_, x, phi, th, batch = as_batch(v, x_hat, phi_hat, theta_hat, p)
        S = np.array(np.broadcast_to(np.asarray(state, dtype=np.float64),
                                     batch + (self.state_size,)), dtype=np.float64)
        args = broadcast_rows(batch, v_, x, phi, th)
        LP = self.law_arrays(dt, batch)
        thn = np.empty(batch + (p,))
        env = law_binding(self, None, ("least_squares_law",), batch == (),
                          lambda: _least_squares_names(self))
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            status = env["least_squares_law"](LP, args[0], args[1], args[2], args[3], dt, thn,
                                              S)
        if status != 0:
            raise UpdateLawError("FilteredLeastSquares: the information R became singular; "
                                 "give a positive-definite Γ₀ of a sensible scale.")
        return thn, S

    def law_arrays(self, dt: float | None, batch: tuple[int, ...] = ()) -> LawArrays:
        """The arrays of :func:`~thetahat.estimation.observer.laws.formulas.least_squares_law`
        for rows of shape ``batch``: the filter's H, L and Φ₁ of ``dt``, Θ and zeroed scratch.

        Parameters
        ----------
        dt : float or None
            The step length; None leaves Φ₁ zero (the compiled kernel points it at the
            observer's Φ₁ of each step: the same φ-function of the same L).
        batch : tuple of int
            The batch shape.

        Returns
        -------
        LawArrays
        """
        filt = self.filter
        if filt is None:
            raise UpdateLawError("FilteredLeastSquares is not bound to an observer: build the "
                                 "observer with it (ModifiedHighGainObserver binds it to its "
                                 "gains), or call for_observer(system, K_x, K_phi).")
        n, _, _, p, k = self.perturbation.dims
        nq = n + k
        Phi1 = (np.zeros((nq, nq)) if dt is None
                else np.array(filt.discrete_phi1(dt), dtype=np.float64))

        def z(*shape: int) -> FloatArray:
            return np.zeros(batch + shape)

        ps = self.parameter_set
        box = ({"lower": np.array(ps.lower), "upper": np.array(ps.upper)}
               if isinstance(ps, Box) else {})
        return LawArrays(H=np.array(filt.H), Lf=np.array(filt.L), Phi1=Phi1, g=z(k),
                         J=z(k, p), w=z(nq, p), wn=z(nq, p), wb=z(nq), Wm=z(k, p), WT=z(p, k),
                         Rn=z(p, p), Rf=z(p, p), b=z(p), e=z(k), Ad=z(nq, nq), Bd=z(nq, k),
                         q=z(nq), pw=z(p + 4, p + 1), **box)

    def __repr__(self) -> str:
        bound = "bound" if self.filter is not None else "unbound"
        return (f"FilteredLeastSquares(p={self.parameter_set.dim}, "
                f"Gamma0={np.round(np.diag(self.Gamma), 6).tolist()}, {bound})")



def _least_squares_names(law: FilteredLeastSquares) -> dict[str, Any]:
    """The hooks of :func:`~thetahat.estimation.observer.laws.formulas.least_squares_law` for
    one law on NumPy rows: g and ∂g/∂θ by the perturbation, the projection by Θ's own
    ``nearest`` in R⁺'s metric (rows already in Θ untouched)."""
    pert = law.perturbation
    n, _, _, p, k = pert.dims
    ps = law.parameter_set

    def g_val(v: FloatArray, x: FloatArray, th: FloatArray, g: FloatArray) -> None:
        g[...] = pert.g(v, x, th)

    def dg_dtheta(v: FloatArray, x: FloatArray, th: FloatArray, J: FloatArray) -> None:
        J[...] = pert.dg_dtheta(v, x, th)

    def project(LP: LawArrays, thn: FloatArray) -> int:
        flat, R = thn.reshape(-1, p), np.broadcast_to(LP.Rn, thn.shape + (p,)).reshape(-1, p, p)
        for i in range(flat.shape[0]):
            if not ps.contains(flat[i]):
                flat[i] = ps.nearest(flat[i], metric=R[i])
        return 0

    return {"g_val": g_val, "dg_dtheta": dg_dtheta, "project": project, "NP": p, "NK": k,
            "NX": n, "NQ": n + k, "FAR": FAR, **status_constants()}
