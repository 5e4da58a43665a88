"""Parameter projection (Krstić, Kanellakopoulos & Kokotović 1995, App. E) and saturation.

Two projections keep θ̂ in the compact convex Θ of Sec. II:

* the continuous-time operator Proj(τ) used in the update laws θ̂̇ = Proj(τ) of Propositions
  1–4 (:meth:`Projection.proj`), and
* the discrete-time projection θ̂ₖ₊₁ = Π_Θ(candidate) used by the ``step`` of the update laws
  (:meth:`Projection.project`).

:func:`saturate` and :class:`Saturation` implement the saturation of x̂ and φ̂ outside boxes X
and Φ suggested in Remark 3 to make an update law globally Lipschitz (Assumption 4).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, final

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from ...._validate import readonly
from ....errors import DimensionError, NonFiniteError, UpdateLawError
from ....model.paramset import Box, ParameterSet

FloatArray = NDArray[np.float64]

__all__ = ["Projection", "Saturation", "saturate"]

#: In the hard projection a constraint P_j counts as active from P_j >= -BOUNDARY_TOL on:
#: points returned by ``nearest`` lie on ∂Θ only up to rounding, and must not be pushed out.
BOUNDARY_TOL = 1e-10
#: Relative tolerance for the symmetry of Γ (products of floats are symmetric to a few ulps).
GAIN_SYMMETRY_RTOL = 1e-10
#: Off-diagonal entries of the Gram matrix ∇Pᵀ Γ ∇P below this fraction of the diagonal are
#: treated as zero (box with diagonal Γ), which makes the constraints decouple exactly.
DECOUPLED_RTOL = 1e-14


def as_gain(name: str, Gamma: Any, p: int) -> FloatArray:
    """Validate an adaptation gain: a scalar γ > 0 (meaning γI) or a (p, p) SPD matrix.

    Raises
    ------
    UpdateLawError
        Γ is not finite, has the wrong shape, is not symmetric, or not positive definite.
    """
    G = np.asarray(Gamma, dtype=np.float64)
    if G.ndim == 0:
        G = G * np.eye(p)
    if G.shape != (p, p):
        raise UpdateLawError(f"{name} must be a positive scalar or a ({p}, {p}) matrix for "
                             f"p = {p} parameters; got shape {G.shape}.")
    if not np.all(np.isfinite(G)):
        raise UpdateLawError(f"{name} contains NaN or inf.")
    scale = max(float(np.max(np.abs(G))), np.finfo(float).tiny)
    if np.max(np.abs(G - G.T)) > GAIN_SYMMETRY_RTOL * scale:
        raise UpdateLawError(f"{name} must be symmetric (Propositions 1–4 use a symmetric "
                             f"positive-definite gain); symmetrise it, e.g. 0.5 * (G + G.T).")
    G = 0.5 * (G + G.T)
    lam = np.linalg.eigvalsh(G)
    if not lam[0] > 0:
        raise UpdateLawError(f"{name} must be positive definite; its smallest eigenvalue is "
                             f"{lam[0]:.3g}. Use a matrix with positive eigenvalues.")
    return G




@final
@dataclass(frozen=True, slots=True, eq=False)
class Projection:
    """The projection operator Proj of Krstić et al. (1995, App. E) for a set Θ and gain Γ.

    Parameters
    ----------
    parameter_set : ParameterSet
        Θ = {θ : P_j(θ) <= 0 for all j}, with the convex functions P_j of
        ``parameter_set.constraint`` (one for a ball, ellipsoid or convex set; one per
        coordinate for a box).
    Gamma : float or array_like, shape (p, p), optional
        The symmetric positive-definite adaptation gain Γ of the update law (default I).
    layer : float, optional
        Width δ >= 0 of the boundary layer, in units of P. ``0`` (the default) is the hard
        projection; ``δ > 0`` is the smooth (Lipschitz in θ̂) variant.

    Notes
    -----
    **Continuous time** (:meth:`proj`). With a single constraint P and a = ∇P(θ̂),

        Proj(τ) = τ                               if P(θ̂) < 0 or aᵀτ <= 0,
        Proj(τ) = τ - c(θ̂) Γ a aᵀ τ / (aᵀ Γ a)    otherwise,

    where c = 1 in the hard variant (the default: it is the operator the proofs of
    Propositions 2–4 cite, and it keeps θ̂ in Θ itself) and c = min(1, 1 + P(θ̂)/δ) in the
    smooth variant, which starts bending τ inside the layer -δ < P <= 0. Both variants
    satisfy the properties of Krstić et al. Lemma E.1 used in the Appendix:
    θ̂(t) stays in Θ, Proj(τ)ᵀΓ⁻¹Proj(τ) <= τᵀΓ⁻¹τ, and -θ̃ᵀΓ⁻¹Proj(τ) <= -θ̃ᵀΓ⁻¹τ with
    θ̃ = θ - θ̂ — for every θ ∈ Θ in the hard variant, and for θ in the shrunken set
    {P <= -δ} in the smooth one (choose Θ slightly larger than the parameter range, as Sec. II
    says).

    Several constraints (the faces of a box, at a corner) are handled together: Proj(τ) is
    the Γ⁻¹-weighted projection of τ onto {w : a_jᵀw <= (1 - c_j) max(a_jᵀτ, 0) for the
    active j}, which reduces to the formula above for one active constraint and keeps the
    three properties. It is solved in closed form when the active constraints decouple
    (a box with diagonal Γ) and by non-negative least squares on the dual otherwise.

    **Discrete time** (:meth:`project`). θ̂ₖ₊₁ = argmin over θ ∈ Θ of (θ - z)ᵀΓ⁻¹(θ - z),
    the nearest point in the Γ⁻¹-weighted norm (Euclidean when Γ = γI). The weighted norm is
    the one of the Lyapunov function V = ½θ̃ᵀΓ⁻¹θ̃ of the proofs, and the projection is
    non-expansive in it: ‖Π(z) - θ‖_Γ⁻¹ <= ‖z - θ‖_Γ⁻¹ for θ ∈ Θ, the discrete analogue of
    Lemma E.1.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws.projection import Projection
    >>> pr = Projection(Box([0.0, 0.0], [1.0, 1.0]))
    >>> pr.proj([1.0, 1.0], [1.0, 0.5]).tolist()  # at the face θ₁ = 1 the outward part is removed
    [0.0, 1.0]
    >>> pr.project([2.0, 0.5]).tolist()
    [1.0, 0.5]
    """

    parameter_set: ParameterSet
    Gamma: FloatArray
    layer: float = 0.0
    _metric: FloatArray | None = field(init=False, repr=False)

    def __init__(self, parameter_set: ParameterSet, Gamma: ArrayLike | None = None, *,
                 layer: float = 0.0) -> None:
        if not isinstance(parameter_set, ParameterSet):
            raise DimensionError(f"parameter_set must be a thetahat ParameterSet (Box, Ball, "
                                 f"Ellipsoid, ConvexSet); got {type(parameter_set).__name__}.")
        p = parameter_set.dim
        G = as_gain("Gamma", 1.0 if Gamma is None else Gamma, p)
        try:
            delta = float(layer)
        except (TypeError, ValueError) as exc:
            raise UpdateLawError(f"layer must be a number >= 0; got {layer!r}.") from exc
        if not (np.isfinite(delta) and delta >= 0):
            raise UpdateLawError(f"layer must be finite and >= 0 (0 = hard projection); got "
                                 f"{delta}.")
        iso = np.allclose(G, G[0, 0] * np.eye(p), rtol=0, atol=GAIN_SYMMETRY_RTOL * G[0, 0])
        object.__setattr__(self, "parameter_set", parameter_set)
        object.__setattr__(self, "Gamma", readonly(G))
        object.__setattr__(self, "layer", delta)
        object.__setattr__(self, "_metric", None if iso else readonly(np.linalg.inv(G)))

    def proj(self, tau: ArrayLike, theta_hat: ArrayLike) -> FloatArray:
        """Proj(τ) at θ̂ (continuous time); τ and θ̂ broadcast, result shape (..., p).

        Parameters
        ----------
        tau : array_like, shape (..., p)
            The unprojected rate, e.g. Γ(θ* - θ̂) in Proposition 1.
        theta_hat : array_like, shape (..., p)
            The current estimate (normally in Θ; points outside are treated as on the boundary).

        Returns
        -------
        ndarray, shape (..., p)
            The projected rate θ̂̇.
        """
        p = self.parameter_set.dim
        tau_ = np.asarray(tau, dtype=np.float64)
        th = np.asarray(theta_hat, dtype=np.float64)
        for name, arr in (("tau", tau_), ("theta_hat", th)):
            if arr.ndim == 0 or arr.shape[-1] != p:
                raise DimensionError(f"{name} must have shape (..., {p}); got {arr.shape}.")
        shape = np.broadcast_shapes(tau_.shape, th.shape)
        t = np.broadcast_to(tau_, shape).reshape(-1, p)
        x = np.broadcast_to(th, shape).reshape(-1, p)
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
            raise NonFiniteError("Proj: tau and theta_hat must be finite.")
        with np.errstate(over="ignore", invalid="ignore"):
            Pj = self.parameter_set.constraint(x)  # (N, q)
            A = self.parameter_set.constraint_grad(x)  # (N, q, p)
        if self.layer == 0.0:
            c = (Pj >= -BOUNDARY_TOL).astype(float)
        else:
            c = np.clip(1.0 + Pj / self.layer, 0.0, 1.0)
        c = np.where(np.isnan(Pj), 1.0, c)
        with np.errstate(over="ignore", invalid="ignore"):
            at = np.einsum("nqp,np->nq", A, t)
        anorm = np.max(np.abs(A), axis=-1)
        J = (c > 0) & (anorm > 0) & np.all(np.isfinite(A), axis=-1)
        r = np.where(J, at - (1.0 - c) * np.maximum(at, 0.0), 0.0)
        rows = np.flatnonzero(np.any(J & (r > 0), axis=-1))
        out = t.copy()
        if rows.size:
            out[rows] = self._correct(t[rows], A[rows], r[rows], J[rows])
        return out.reshape(shape)

    def _correct(self, t: FloatArray, A: FloatArray, r: FloatArray,
                 J: NDArray[np.bool_]) -> FloatArray:
        """τ - Γ Aᵀμ with μ >= 0 the dual solution of the weighted projection (rows need it)."""
        A = np.where(J[..., None], A, 0.0)
        GA = A @ self.Gamma  # rows Γ a_j (Γ symmetric)
        H = GA @ np.swapaxes(A, -1, -2)  # (N, q, q) Gram matrix a_iᵀ Γ a_j
        d = np.einsum("nqq->nq", H)
        off = H - d[..., :, None] * np.eye(H.shape[-1])
        tiny = DECOUPLED_RTOL * np.sqrt(np.abs(d[..., :, None] * d[..., None, :]))
        dec = np.all(np.abs(off) <= tiny, axis=(-2, -1)) | (np.sum(J, axis=-1) <= 1)
        safe_d = np.where(d > 0, d, 1.0)
        mu = np.where(J & (d > 0), np.maximum(r, 0.0) / safe_d, 0.0)
        for i in np.flatnonzero(~dec):
            idx = np.flatnonzero(J[i])
            Hs = H[i][np.ix_(idx, idx)]
            L = np.linalg.cholesky(Hs + np.finfo(float).eps * np.trace(Hs) * np.eye(idx.size))
            sol, _ = scipy.optimize.nnls(L.T, np.linalg.solve(L, r[i, idx]))
            mu[i] = 0.0
            mu[i, idx] = sol
        return t - np.einsum("nq,nqp->np", mu, GA)

    def project(self, theta: ArrayLike) -> FloatArray:
        """Nearest point of Θ in the Γ⁻¹-weighted norm (discrete time); shape (..., p)."""
        th = np.asarray(theta, dtype=np.float64)
        if self._metric is None:
            return self.parameter_set.nearest(th)
        return self.parameter_set.nearest(th, metric=self._metric)

    def __repr__(self) -> str:
        kind = "hard" if self.layer == 0 else f"smooth, layer={self.layer}"
        return (f"Projection({self.parameter_set!r}, Gamma={self.Gamma.tolist()}, {kind})")


def _margin(margin: Any) -> float:
    try:
        m = float(margin)
    except (TypeError, ValueError) as exc:
        raise UpdateLawError(f"margin must be a number >= 0; got {margin!r}.") from exc
    if not (np.isfinite(m) and m >= 0):
        raise UpdateLawError(f"margin must be finite and >= 0 (0 = hard clip); got {m}.")
    return m


def saturate(value: ArrayLike, box: Box, *, margin: float = 0.0) -> FloatArray:
    """Saturate ``value`` outside ``box`` (Remark 3); identity inside the box.

    Parameters
    ----------
    value : array_like, shape (..., d)
    box : Box
        The box X (for x̂) or Φ (for φ̂) known to contain the true values.
    margin : float, optional
        ``0`` (default): hard saturation, a clip to the box. ``m > 0``: smooth saturation,
        ``upper + m tanh((value - upper)/m)`` above the box and the mirror image below, which
        is C² and stays within ``m`` of the box.

    Returns
    -------
    ndarray, shape (..., d)

    Notes
    -----
    Both variants are the identity on the box and globally Lipschitz with constant 1, so an
    update law that is only locally Lipschitz in (x̂, φ̂) becomes globally Lipschitz
    (Assumption 4) without changing its value at the true (x, φ). The hard clip is cheaper;
    the smooth variant keeps the right-hand side differentiable for stiff ODE solvers.

    Examples
    --------
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws.projection import saturate
    >>> saturate([-3.0, 0.5, 3.0], Box([-1.0] * 3, [1.0] * 3)).tolist()
    [-1.0, 0.5, 1.0]
    """
    if not isinstance(box, Box):
        raise DimensionError(f"box must be a thetahat Box; got {type(box).__name__}.")
    m = _margin(margin)
    val = np.asarray(value, dtype=np.float64)
    if val.ndim == 0 or val.shape[-1] != box.dim:
        raise DimensionError(f"value must have shape (..., {box.dim}) to match the box; got "
                             f"{val.shape}.")
    if m == 0.0:
        return np.clip(val, box.lower, box.upper)
    above = box.upper + m * np.tanh((val - box.upper) / m)
    below = box.lower - m * np.tanh((box.lower - val) / m)
    return np.where(val > box.upper, above, np.where(val < box.lower, below, val))


@final
@dataclass(frozen=True, slots=True, eq=False)
class Saturation:
    """Saturation of x̂ outside X and φ̂ outside Φ before an update law uses them (Remark 3).

    Parameters
    ----------
    x_box : Box, optional
        X, a box known to contain x (no saturation of x̂ when None).
    phi_box : Box, optional
        Φ, a box known to contain φ (no saturation of φ̂ when None).
    margin : float, optional
        0 for a hard clip (default), > 0 for the smooth saturation of :func:`saturate`.

    Examples
    --------
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws.projection import Saturation
    >>> sat = Saturation(phi_box=Box([-2.0], [2.0]))
    >>> x, phi = sat.apply([[0.0, 9.0]], [[5.0]])
    >>> phi.tolist()
    [[2.0]]
    """

    x_box: Box | None = None
    phi_box: Box | None = None
    margin: float = 0.0

    def __init__(self, x_box: Box | None = None, phi_box: Box | None = None, *,
                 margin: float = 0.0) -> None:
        for name, box in (("x_box", x_box), ("phi_box", phi_box)):
            if box is not None and not isinstance(box, Box):
                raise DimensionError(f"{name} must be a thetahat Box or None; got "
                                     f"{type(box).__name__}.")
        object.__setattr__(self, "x_box", x_box)
        object.__setattr__(self, "phi_box", phi_box)
        object.__setattr__(self, "margin", _margin(margin))

    def apply(self, x_hat: ArrayLike, phi_hat: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return (sat(x̂), sat(φ̂)), shapes unchanged."""
        x = np.asarray(x_hat, dtype=np.float64)
        phi = np.asarray(phi_hat, dtype=np.float64)
        if self.x_box is not None:
            x = saturate(x, self.x_box, margin=self.margin)
        if self.phi_box is not None:
            phi = saturate(phi, self.phi_box, margin=self.margin)
        return x, phi
