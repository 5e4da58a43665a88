r"""The modified high-gain observer (3) of Sec. III, with the parameter estimator (8) in the loop.

State ``s = col(x̂, z, θ̂)`` (plus ``x̂₂`` when a :class:`SecondObserver` is attached, and the
update law's own state when it has one), and

$$
\begin{aligned}
\dot{\hat x} &= A\hat x + Bu + E\hat\phi + K_x(\varepsilon)(y - C\hat x), && \text{(3a)} \\
\dot z &= -\frac{\partial g}{\partial\theta}(v, \hat x, \hat\theta)\,\dot{\hat\theta}
  - \frac{\partial g}{\partial x}(v, \hat x, \hat\theta)\,K_x(\varepsilon)(y - C\hat x)
  + K_\phi(\varepsilon)(y - C\hat x), && \text{(3b)} \\
\hat\phi &= g(v, \hat x, \hat\theta) + z, && \text{(3c)} \\
\dot{\hat\theta} &= u_\theta(v, \hat x, \hat\phi, \hat\theta). && \text{(8)}
\end{aligned}
$$

What lives here: :class:`ModifiedHighGainObserver` — its construction and checks, its plan per
step length, and its three uses: ``rhs`` for ODE integrators, ``init``/``step`` for streaming,
``run`` for logged sample arrays — and :class:`ObserverEstimate`, what ``estimate`` reads from
one state. The discrete step is that of :mod:`thetahat.estimation.observer.step` over the
observer's :meth:`~ModifiedHighGainObserver.plan`; the loop of ``run`` over a record, its
status and its result live in :mod:`thetahat.estimation.observer.record_run`, shared with the
other back ends, which :func:`thetahat.estimation.drive.runner` chooses among. The state is
always passed explicitly.

What it may import: the rest of this room (plan, step, record_run, redesign, laws), the
bottom of :mod:`thetahat.estimation` (protocol, records, drive, status), the model, the
structure checks and the package's helpers; never :mod:`thetahat.codegen` or the statistical
estimators.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_matrix, as_vector, check_finite, readonly
from ...errors import DimensionError, NonFiniteError, UnsupportedError
from ...limits import check_allocation
from ...model.system import PerturbedLinearSystem
from ...structure.assumptions import check_assumption_1
from ..drive import runner
from ..protocol import EstimateResult, check_sample, check_state, check_step_length
from ..records import check_nan_policy, check_records
from ..status import Status
from .laws import UpdateLaw
from .plan import StateLayout, StepPlan, StepPlans
from .record_run import (Failure, Progress, check_compiled, check_hold, integrate_record,
                         observer_result, step_error)
from .redesign import SecondObserver
from .step import advance, diverged, observer_forcing, second_forcing

__all__ = ["ModifiedHighGainObserver", "ObserverEstimate"]

FloatArray = NDArray[np.float64]

def _vec(name: str, a: Any, size: int, *, finite: bool = True) -> FloatArray:
    """``as_vector`` with a fast path for float64 arrays of the right shape (hot loop)."""
    if type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (size,):
        arr = a
    else:
        arr = as_vector(name, a, size, finite=False)
    # One dot product detects NaN/inf; the exact check (and its message) runs only then.
    if finite and not math.isfinite(float(arr @ arr)):
        check_finite(name, arr)
    return arr


@dataclass(frozen=True, slots=True, eq=False)
class ObserverEstimate:
    """Estimates read from one streaming state (:meth:`ModifiedHighGainObserver.estimate`).

    Attributes
    ----------
    x_hat : ndarray, shape (n,)
    phi_hat : ndarray, shape (k,)
    theta_hat : ndarray, shape (p,)
    x_hat_refined : ndarray, shape (n,), or None
    """

    x_hat: FloatArray
    phi_hat: FloatArray
    theta_hat: FloatArray
    x_hat_refined: FloatArray | None


@dataclass(frozen=True, slots=True, eq=False)
class ModifiedHighGainObserver:
    r"""Modified high-gain observer (3) with update law (8): estimates x, φ and θ.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The plant (1); ``system.perturbation`` (g and its Jacobians) is required.
    K_x : array_like, shape (n, r)
        Gain K_x(ε) of (3a).
    K_phi : array_like, shape (k, r)
        Gain K_φ(ε) of (3b).
    update_law : UpdateLaw
        The parameter estimator (8); θ̂ stays in ``update_law.parameter_set``.
    second : SecondObserver, optional
        The second observer of Sec. VI; its state x̂₂ is appended to the observer state and
        ``run`` reports it as ``x_hat_refined``.
    allow_nonminimum_phase : bool, default False
        Build the observer even when (C, A, E) violates Assumption 1 (the estimation error
        then diverges; only for studying the failure).
    nan_policy : {"raise", "skip"}, default "raise"
        What a NaN in y means. ``"raise"``: :class:`~thetahat.errors.NonFiniteError`
        (before anything is integrated, in ``run``). ``"skip"``: the sample is missing and the
        observer predicts over that interval: y is replaced by ``C x̂`` everywhere (so the
        output injection vanishes and g sees the predicted output), θ̂ is frozen and z is
        constant. NaN is never propagated into the state. NaN in u, and inf anywhere, always
        raise.
    hold : {"zoh", "foh"}, default "zoh"
        How ``run`` treats the samples between two instants: held constant (``"zoh"``;
        identical to a loop of :meth:`step`, which always holds them: it is causal) or
        interpolated linearly to the next sample (``"foh"``; non-causal, one more evaluation
        of g per step, a smaller error when the signals are smooth). See Notes.
    progress : callable, optional
        ``progress(done, total)``, called by ``run`` every
        :data:`~thetahat.estimation.observer.record_run.PROGRESS_EVERY` samples and at the
        end (e.g. :func:`thetahat.progress.reporter`).
    compiled : {False, None, True}, default False
        Where ``run`` runs: ``False``, the NumPy step here; ``None``, on the fastest back end
        where it pays for the record (:func:`~thetahat.estimation.drive.runner`: the C, or
        numba's kernel on long records); ``True``, on the fastest back end that takes the
        observer. A back end that cannot take it leaves the record to the next one, down to
        NumPy. Every back end gives the same estimates to rounding.

    Attributes
    ----------
    layout : StateLayout
        Dimensions and the offsets of x̂, z, θ̂, x̂₂ and the law's state in the state vector.

    Raises
    ------
    DimensionError
        Shapes disagree with the system, the system has no perturbation, or Θ of the update
        law has the wrong dimension.
    NotMinimumPhaseError, NotLeftInvertibleError
        (C, A, E) violates Assumption 1 (unless ``allow_nonminimum_phase``); the message
        names the zeros.
    NonFiniteError
        A gain holds NaN or inf.
    OptionError
        Unknown ``nan_policy``, ``hold`` or ``compiled``.

    Notes
    -----
    **One step, several back ends.** ``step`` and ``run`` are the batch of one of
    :func:`thetahat.estimation.observer.step.advance`, which
    :func:`~thetahat.estimation.observer.batch_run.run_batch` runs for B rows; the matrices, gains and
    φ-matrices come from the frozen :meth:`plan` (one per step length). The state is
    ``col(x̂, z, θ̂[, x̂₂][, law state])`` (:attr:`layout`). A step whose state norm exceeds
    :data:`~thetahat.estimation.observer.formulas.DIVERGENCE_BOUND` (or is NaN/inf) fails with
    the same :class:`~thetahat.estimation.status.Status` and the same message naming the step
    in every back end: ``step`` and ``run`` raise its :class:`~thetahat.errors.NonFiniteError`,
    ``run(..., throw=False)`` returns it in the result.

    **Discretisation.** ``step`` and ``run`` use the exponential, linearly implicit step of
    :mod:`thetahat.estimation.observer.discretize` on ``(x̂, z)`` (its module docstring gives
    the observer's constant part L, its state-dependent part N and what follows: g ≡ 0 is the
    exactly discretised Luenberger observer of (2), the 1/ε scaling never limits the step
    length, a stiff g is handled stably). θ̂ is advanced by ``update_law.advance`` (so it
    stays in Θ) and z receives ``−∂g/∂θ Δθ̂``, the discrete form of the first term of (3b).

    **Hold.** ``hold`` chooses how ``run`` treats the samples between two instants; the
    errors of each choice on the DC motor of Sec. VIII are tabulated in
    :mod:`thetahat.estimation.observer.record_run`.

    ``v̇`` is never needed: z absorbs ∂g/∂v v̇ (Sec. III).

    **The estimator protocol.** The observer is an
    :class:`~thetahat.estimation.protocol.Estimator`: its state is the array above (not a
    wrapper object: ``rhs`` and ODE solvers integrate it as it is), ``run`` returns an
    :class:`~thetahat.estimation.protocol.EstimateResult` whose ``diagnostics`` is an
    :class:`~thetahat.estimation.protocol.ObserverDiagnostics`; the hold, the progress
    callback and the back end are the observer's own (:meth:`with_run_options`), so code that
    takes any estimator runs it as it was built.

    References
    ----------
    H. F. Grip, A. Saberi and T. A. Johansen, "State and parameter estimation for linear
    systems with nonlinearly parameterized perturbations", eqs. (2)–(4), (8), Secs. III, VI.

    Examples
    --------
    With g ≡ 0 and a constant θ̂ the observer is a Luenberger observer for (2):

    >>> import numpy as np
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.model.perturbation import CallablePerturbation
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws import ConstantLaw
    >>> zero = CallablePerturbation(g=lambda v, x, th: 0 * x, n=1, m=1, r=1, p=1, k=1)
    >>> plant = PerturbedLinearSystem(A=[[-1.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]],
    ...                               perturbation=zero)
    >>> law = ConstantLaw([0.5], Box([0.0], [1.0]))
    >>> obs = ModifiedHighGainObserver(system=plant, K_x=[[7.0]], K_phi=[[12.0]],
    ...                                update_law=law)     # poles −2, −6
    >>> t = np.arange(0.0, 5.0, 1e-3)
    >>> y = 1.0 + 0 * t                       # x ≡ 1 with u = 0 needs φ ≡ 1
    >>> res = obs.run(t, np.zeros_like(t), y)
    >>> bool(abs(res.phi_hat[-1, 0] - 1.0) < 1e-3)
    True

    Streaming, and the same right-hand side for an ODE solver:

    >>> s = obs.init(x_hat0=[0.5])
    >>> for _ in range(1000):
    ...     s = obs.step(s, u=[0.0], y=[1.0], dt=1e-3)
    >>> from scipy.integrate import solve_ivp
    >>> sol = solve_ivp(lambda t, q: obs.rhs(t, q, [0.0, 1.0]), (0.0, 1.0),
    ...                 obs.init(x_hat0=[0.5]), method="Radau", rtol=1e-10, atol=1e-12)
    >>> bool(np.allclose(s, sol.y[:, -1], atol=1e-8))     # exact for g ≡ 0 and a held y
    True
    """

    system: PerturbedLinearSystem
    K_x: FloatArray
    K_phi: FloatArray
    update_law: UpdateLaw
    second: SecondObserver | None
    nan_policy: str
    hold: str
    progress: Progress | None
    compiled: bool | None
    layout: StateLayout
    _plans: StepPlans

    def __init__(self, *, system: PerturbedLinearSystem, K_x: Any, K_phi: Any,
                 update_law: UpdateLaw, second: SecondObserver | None = None,
                 nan_policy: str = "raise", hold: str = "zoh",
                 progress: Progress | None = None, compiled: bool | None = False,
                 allow_nonminimum_phase: bool = False) -> None:
        if not isinstance(system, PerturbedLinearSystem):
            raise DimensionError("system must be a PerturbedLinearSystem; got "
                                 f"{type(system).__name__}.")
        system.require_perturbation("ModifiedHighGainObserver")
        if not allow_nonminimum_phase:           # Assumption 1, or the error cannot converge
            check_assumption_1(system.A, system.E, system.C, strict=True)
        n, m, r, k, p = system.n, system.m, system.r, system.k, system.p
        Kx = readonly(as_matrix("K_x", K_x, (n, r)))
        Kphi = readonly(as_matrix("K_phi", K_phi, (k, r)))
        if not isinstance(update_law, UpdateLaw):
            raise DimensionError("update_law must be a thetahat UpdateLaw; got "
                                 f"{type(update_law).__name__}.")
        if update_law.parameter_set.dim != p:
            raise DimensionError(f"update_law.parameter_set has dimension "
                                 f"{update_law.parameter_set.dim} but the perturbation has "
                                 f"p = {p} parameters.")
        if second is not None:
            if not isinstance(second, SecondObserver):
                raise DimensionError("second must be a SecondObserver; got "
                                     f"{type(second).__name__}.")
            s2 = second.system
            if (s2.n, s2.m, s2.r, s2.k, s2.p) != (n, m, r, k, p):
                raise DimensionError(
                    f"second observer's system has (n, m, r, k, p) = "
                    f"{(s2.n, s2.m, s2.r, s2.k, s2.p)}; the observer's has {(n, m, r, k, p)}.")
        check_nan_policy(nan_policy)
        check_hold(hold)
        check_compiled(compiled)
        update_law = update_law.for_observer(system, Kx, Kphi)
        layout = StateLayout(n=n, m=m, r=r, k=k, p=p, second=second is not None,
                             law_size=int(update_law.state_size))
        plans = StepPlans(A=system.A, B=system.B, C=system.C, E=system.E, K_x=Kx, K_phi=Kphi,
                          p=p, Gamma=update_law.gain, law_size=layout.law_size,
                          second=None if second is None else second.plan,
                          predict=nan_policy == "skip")
        for name, val in (("system", system), ("K_x", Kx), ("K_phi", Kphi),
                          ("update_law", update_law), ("second", second),
                          ("nan_policy", nan_policy), ("hold", hold), ("progress", progress),
                          ("compiled", compiled), ("layout", layout), ("_plans", plans)):
            object.__setattr__(self, name, val)

    @classmethod
    def from_design(cls, system: PerturbedLinearSystem, design: Any, update_law: UpdateLaw,
                    *, second: SecondObserver | None = None, nan_policy: str = "raise",
                    hold: str = "zoh", allow_nonminimum_phase: bool = False
                    ) -> ModifiedHighGainObserver:
        """Build from a gain design on the extended system (reads ``design.K_x``,
        ``design.K_phi``).

        Parameters
        ----------
        system, update_law, second, nan_policy, hold, allow_nonminimum_phase
            As for the constructor.
        design : GainDesign
            Any object with attributes ``K_x`` (n, r) and ``K_phi`` (k, r).

        Returns
        -------
        ModifiedHighGainObserver

        Examples
        --------
        >>> from types import SimpleNamespace
        >>> from thetahat.model.system import PerturbedLinearSystem
        >>> from thetahat.model.perturbation import CallablePerturbation
        >>> from thetahat.model.paramset import Box
        >>> from thetahat.estimation.observer.laws import ConstantLaw
        >>> zero = CallablePerturbation(g=lambda v, x, th: 0 * x, n=1, m=1, r=1, p=1, k=1)
        >>> plant = PerturbedLinearSystem(A=[[-1]], B=[[1]], C=[[1]], E=[[1]],
        ...                               perturbation=zero)
        >>> design = SimpleNamespace(K_x=[[3.0]], K_phi=[[2.0]])
        >>> law = ConstantLaw([0.5], Box([0.0], [1.0]))
        >>> ModifiedHighGainObserver.from_design(plant, design, law).K_phi
        array([[2.]])
        """
        return cls(system=system, K_x=design.K_x, K_phi=design.K_phi, update_law=update_law,
                   second=second, nan_policy=nan_policy, hold=hold,
                   allow_nonminimum_phase=allow_nonminimum_phase)

    # ------------------------------------------------------------------ layout
    @property
    def state_size(self) -> int:
        """Length of the state vector: n + k + p (+ n with a second observer, + the law's)."""
        return self.layout.size

    def plan(self, dt: float) -> StepPlan:
        """The :class:`~thetahat.estimation.observer.plan.StepPlan` of this observer for step length dt.

        Computed once per step length (to 12 significant digits) and cached (with the
        prediction's φ-matrices only under ``nan_policy="skip"``); every back end
        (``step``/``run``, :func:`~thetahat.estimation.observer.batch_run.run_batch`, the compiled
        kernel) reads the observer's matrices, gains and φ-matrices from it.

        Parameters
        ----------
        dt : float
            Step length > 0.

        Returns
        -------
        StepPlan

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> obs = lugre.observer()
        >>> obs.plan(1e-3) is obs.plan(1e-3 * (1 + 1e-15))
        True
        """
        return self._plans(dt)

    def _split(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray,
                                             FloatArray | None]:
        lay = self.layout
        return s[lay.x], s[lay.z], s[lay.theta], (s[lay.x2] if lay.second else None)

    def check_samples(self, u: ArrayLike | None, y: ArrayLike) -> tuple[FloatArray, FloatArray, bool]:
        """Validate one pair of samples against the NaN policy.

        Parameters
        ----------
        u : array_like, shape (m,)
            Input sample (``None`` when m = 0); must be finite.
        y : array_like, shape (r,)
            Output sample; NaN marks a missing sample under ``nan_policy="skip"``.

        Returns
        -------
        u : ndarray, shape (m,)
        y : ndarray, shape (r,)
        correct : bool
            False when y is missing (the step predicts).

        Raises
        ------
        DimensionError
            Wrong shapes.
        NonFiniteError
            NaN or inf in u; inf in y; NaN in y under ``nan_policy="raise"``.
        """
        u_, y_ = check_sample(self.layout, u, y)
        if math.isfinite(float(y_ @ y_)):
            return u_, y_, True
        if self.nan_policy == "raise":
            raise NonFiniteError("y contains NaN and nan_policy='raise'; pass "
                                 "nan_policy='skip' to the observer to predict over missing "
                                 "samples, or clean the data.")
        return u_, y_, False

    def check_state(self, state: ArrayLike) -> FloatArray:
        """Validate an observer state (shape (state_size,), finite).

        Parameters
        ----------
        state : array_like, shape (state_size,)

        Returns
        -------
        ndarray, shape (state_size,)

        Raises
        ------
        DimensionError, NonFiniteError
            Wrong shape, or NaN or inf (a diverged or badly initialised state).
        """
        size = self.layout.size
        if (type(state) is np.ndarray and state.dtype == np.float64 and state.shape == (size,)
                and all(map(math.isfinite, state.tolist()))):
            return state                    # fast path: what the checks below accept
        s = check_state("ModifiedHighGainObserver", state, None, {"state": (size,)})
        if not np.isfinite(s).all():
            raise NonFiniteError("the observer state holds NaN or inf: it has diverged or was "
                                 "initialised badly; restart from init().")
        return s

    def check_records(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike,
                      batch: int | None = None) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray,
                                 NDArray[np.bool_]]:
        """Validate sampled records against the NaN policy (before anything is integrated).

        :func:`~thetahat.estimation.records.check_records` with this observer's layout and
        ``nan_policy``.

        Parameters
        ----------
        t : array_like, shape (N,)
            Strictly increasing sampling instants.
        u : array_like, shape ([B,] N, m), or ([B,] N) when m = 1
            ``None`` when m = 0.
        y : array_like, shape ([B,] N, r), or ([B,] N) when r = 1
        batch : int, optional
            None: one record (no leading axis); else the records carry a leading axis of
            length B (-1: any B).

        Returns
        -------
        t, dts : ndarray, shapes (N,), (N - 1,)
        U, Y : ndarray, shapes (B, N, m), (B, N, r)
            B = 1 for a single record.
        ok : ndarray of bool, shape (B, N)
            Samples whose y is present.

        Raises
        ------
        DimensionError
            Wrong shapes, or ``t`` not strictly increasing.
        NonFiniteError
            NaN or inf in t or u; inf in y; NaN in y under ``nan_policy="raise"``.
        """
        return check_records(self.layout, self.nan_policy, t, u, y, batch)


    # ------------------------------------------------------------------ public API
    def rhs(self, t: float, state: ArrayLike, v: ArrayLike,
            v_dot: ArrayLike | None = None) -> FloatArray:
        """Time derivative of the observer state, (3a)–(3c) and (8), for ODE integrators.

        Parameters
        ----------
        t : float
            Time (unused: given v the observer is time-invariant).
        state : array_like, shape (state_size,)
            col(x̂, z, θ̂) (+ x̂₂ with a second observer).
        v : array_like, shape (m + r,)
            col(u, y) at time t.
        v_dot : array_like, optional
            Accepted for integrators that supply v̇ (the paper's d); (3) does not use it
            because z absorbs ∂g/∂v v̇.

        Returns
        -------
        ndarray, shape (state_size,)

        Raises
        ------
        DimensionError
            Wrong shapes.
        NonFiniteError
            NaN or inf in the state or u; inf in y; NaN in y under ``nan_policy="raise"``.

        Notes
        -----
        For ``scipy.integrate.solve_ivp`` wrap it with the signals, e.g.
        ``solve_ivp(lambda t, s: obs.rhs(t, s, v_of(t)), (t0, t1), s0, method="Radau")``
        (the class example integrates it).
        """
        lay = self.layout
        v_ = _vec("v", v, lay.m + lay.r, finite=False)
        u, y, correct = self.check_samples(v_[:lay.m], v_[lay.m:])
        s = self.check_state(state)
        if lay.law_size:
            raise UnsupportedError(f"rhs: {type(self.update_law).__name__} carries a state "
                                   "that is defined by its discrete step only; use step/run.")
        x, _, th, x2 = self._split(s)
        pert = self.system.require_perturbation("ModifiedHighGainObserver")
        plan = self._plans.continuous()
        F, phi, _, vv = observer_forcing(plan, pert, s[:lay.n + lay.k], th, u, y, correct)
        parts = [F]
        if correct:
            th_dot = np.asarray(self.update_law.rate(vv, x, phi, th),
                                dtype=np.float64).reshape(th.shape)
            F[lay.n:] -= pert.dg_dtheta(vv, x, th) @ th_dot
        else:
            th_dot = np.zeros_like(th)
        parts.append(th_dot)
        if x2 is not None and self.second is not None:
            F2, _ = second_forcing(self.second.plan(None), pert, x2, u, y, th, correct)
            parts.append(F2)
        return np.concatenate(parts)

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None,
             z0: ArrayLike | None = None,
             x_hat_refined0: ArrayLike | None = None) -> FloatArray:
        """Initial observer state col(x̂₀, z₀, θ̂₀[, x̂₂₀]).

        Parameters
        ----------
        x_hat0 : array_like, shape (n,), optional
            Default zeros.
        theta_hat0 : array_like, shape (p,), optional
            Must lie in Θ; validated by ``update_law.init`` (whose default is used when
            omitted: the centre of Θ, or the held value of a ``ConstantLaw``).
        z0 : array_like, shape (k,), optional
            Default zeros (φ̂₀ = g(v₀, x̂₀, θ̂₀)).
        x_hat_refined0 : array_like, shape (n,), optional
            Second observer's x̂₂₀ (default x̂₀); only with a second observer.

        Returns
        -------
        ndarray, shape (state_size,)

        Raises
        ------
        ParameterSetError
            θ̂₀ outside Θ.
        DimensionError, NonFiniteError
            Wrong shape or non-finite entries.
        """
        lay = self.layout
        n, k, p = lay.n, lay.k, lay.p
        x0 = np.zeros(n) if x_hat0 is None else as_vector("x_hat0", x_hat0, n)
        zz = np.zeros(k) if z0 is None else as_vector("z0", z0, k)
        th0 = np.asarray(self.update_law.init(theta_hat0), dtype=np.float64).reshape(p)
        parts = [x0, zz, th0]
        if self.second is not None:
            parts.append(x0.copy() if x_hat_refined0 is None
                         else as_vector("x_hat_refined0", x_hat_refined0, n))
        elif x_hat_refined0 is not None:
            raise DimensionError("x_hat_refined0 given but no second observer is attached.")
        if lay.law_size:
            parts.append(np.asarray(self.update_law.init_state(th0),
                                    dtype=np.float64).reshape(lay.law_size))
        return np.concatenate(parts)

    def step(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike, dt: float) -> FloatArray:
        """Advance the state by ``dt``, holding the current samples (zero-order hold).

        Parameters
        ----------
        state : array_like, shape (state_size,)
            The state at the time of the samples.
        u : array_like, shape (m,)
            Current input sample (``None`` when m = 0).
        y : array_like, shape (r,)
            Current output sample; NaN handled per ``nan_policy``.
        dt : float
            Time to the next sample, > 0.

        Returns
        -------
        ndarray, shape (state_size,)
            The state dt later.

        Raises
        ------
        DimensionError, NonFiniteError
            As for :meth:`rhs`; also dt <= 0.
        """
        u_, y_, correct = self.check_samples(u, y)
        s = self.check_state(state)
        return self._advance(s, u_, y_, check_step_length(dt), correct)

    def estimate(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike) -> ObserverEstimate:
        """Read x̂, φ̂ = g(v, x̂, θ̂) + z (3c), θ̂ (and x̂₂) from a state and the current samples.

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
        y : array_like, shape (r,)
            NaN (with ``nan_policy="skip"``) evaluates g at the predicted output C x̂.

        Returns
        -------
        ObserverEstimate
        """
        u_, y_, correct = self.check_samples(u, y)
        x, z, th, x2 = self._split(self.check_state(state))
        v = np.concatenate((u_, y_ if correct else self.system.C @ x))
        phi = self.system.require_perturbation("estimate").g(v, x, th) + z
        return ObserverEstimate(x_hat=x.copy(), phi_hat=np.asarray(phi, dtype=np.float64),
                                theta_hat=th.copy(),
                                x_hat_refined=None if x2 is None else x2.copy())

    def read_estimates(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike
                       ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """x̂, θ̂ and x̂₂ of a state, without φ̂: :meth:`estimate` with the same checks of
        the state and the samples, for a caller that does not use φ̂ (the guarded
        estimator's stage 1).

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
        y : array_like, shape (r,)
            Checked as by :meth:`estimate` (NaN only under ``nan_policy="skip"``).

        Returns
        -------
        x_hat : ndarray (n,)
        theta_hat : ndarray (p,)
        x_hat_refined : ndarray (n,) or None
            x̂₂ of the second observer (None without one). Copies, not views of ``state``.

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> obs = lugre.observer()
        >>> x, th, x2 = obs.read_estimates(obs.init(theta_hat0=[0.3]), [0.0], [0.0])
        >>> th.tolist(), x.shape, x2.shape              # LuGre's has the second observer
        ([0.3], (2,), (2,))
        """
        self.check_samples(u, y)
        return self.layout.read(self.check_state(state))

    def read_and_step(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike, dt: float
                      ) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray]:
        """:meth:`read_estimates` and :meth:`step` of one state and sample, checked once.

        What a stream that reads the estimates at each sample before advancing calls (the
        guarded estimator's stage 1): the same checks, errors and results as the two calls.

        Parameters
        ----------
        state, u, y, dt
            As :meth:`step`.

        Returns
        -------
        x_hat, theta_hat, x_hat_refined
            As :meth:`read_estimates`, at the time of the samples.
        state : ndarray, shape (state_size,)
            The state dt later, as :meth:`step`.

        Raises
        ------
        DimensionError, NonFiniteError, UpdateLawError
            As :meth:`step` (a refused sample or state before anything is read).

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> obs = lugre.observer()
        >>> s0 = obs.init(theta_hat0=[0.3])
        >>> x, th, x2, s1 = obs.read_and_step(s0, [0.5], [0.0], 1e-3)
        >>> th.tolist(), bool((s1 == obs.step(s0, [0.5], [0.0], 1e-3)).all())
        ([0.3], True)
        """
        u_, y_, correct = self.check_samples(u, y)
        s = self.check_state(state)
        return (*self.layout.read(s), self._advance(s, u_, y_, check_step_length(dt), correct))

    def _advance(self, s: FloatArray, u: FloatArray, y: FloatArray, h: float,
                 correct: bool) -> FloatArray:
        """One step of checked arrays (the body of :meth:`step`)."""
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            nxt = advance(self.plan(h), self.system.require_perturbation("step"),
                          self.update_law, s, u, y, h, correct)
        if diverged(nxt):
            raise step_error(Status.DIVERGED, type(self.update_law).__name__)
        return nxt

    def with_run_options(self, *, hold: str | None = None,
                         progress: Progress | None | bool = False,
                         compiled: bool | None | str = "keep") -> ModifiedHighGainObserver:
        """This observer with another hold, progress callback or back end for ``run``.

        The estimator itself (system, gains, law, second observer, NaN policy) and the plans
        computed so far are shared.

        Parameters
        ----------
        hold : {"zoh", "foh"}, optional
            Default: unchanged.
        progress : callable or None, optional
            ``progress(done, total)``; None removes the callback. Default: unchanged.
        compiled : {False, None, True}, optional
            Default: unchanged.

        Returns
        -------
        ModifiedHighGainObserver

        Raises
        ------
        OptionError
            Unknown ``hold`` or ``compiled``.

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> obs = lugre.observer()
        >>> foh = obs.with_run_options(hold="foh")
        >>> foh.hold, obs.hold, foh.update_law is obs.update_law
        ('foh', 'zoh', True)
        """
        new = object.__new__(type(self))
        for name in ("system", "K_x", "K_phi", "update_law", "second", "nan_policy", "hold",
                     "progress", "compiled", "layout", "_plans"):
            object.__setattr__(new, name, getattr(self, name))
        if hold is not None:
            object.__setattr__(new, "hold", check_hold(hold))
        if progress is not False:
            object.__setattr__(new, "progress", progress)
        if compiled != "keep":
            object.__setattr__(new, "compiled", check_compiled(compiled))
        return new

    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            state0: ArrayLike | None = None, throw: bool = True) -> EstimateResult:
        """Run the observer over sampled records (logged data), with its ``hold``.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sampling instants, finite and strictly increasing (any spacing).
        u : array_like, shape (N, m) or (N,) when m = 1
            Input samples (``None`` when m = 0).
        y : array_like, shape (N, r) or (N,) when r = 1
            Output samples; NaN handled per ``nan_policy`` (checked before integrating).
        state0 : array_like, shape (state_size,), optional
            Initial state at ``t[0]``; default ``init()``.
        throw : bool, default True
            What a failed step does (a state that diverges, a singular implicit step, an
            invalid θ* under ``on_invalid='raise'``): True raises its error; False returns
            the result with ``status`` and ``message`` saying why, ``failed_at`` the first
            row not computed, and the rows from there NaN
            (:mod:`~thetahat.estimation.observer.record_run`).

        Returns
        -------
        EstimateResult
            Row k holds the state at ``t[k]`` (before sample k is processed: the state
            ``step`` returns after samples 0 … k − 1); ``diagnostics`` is an
            :class:`~thetahat.estimation.protocol.ObserverDiagnostics` (x̂₂ of the second
            observer, also read as ``result.x_hat_refined``).

        Raises
        ------
        DimensionError
            Wrong shapes, or ``t`` not strictly increasing.
        NonFiniteError
            NaN or inf in t or u; inf in y; NaN in y under ``nan_policy="raise"``; with
            ``throw``, the state diverged (the message names the step and the fix).
        UpdateLawError
            With ``throw``: θ* invalid where the weight is positive (``on_invalid='raise'``).

        Examples
        --------
        Outputs scaled far beyond the model (× 1e100): the first step leaves every bound, and
        with ``throw=False`` the run says so instead of raising.

        >>> import numpy as np
        >>> from thetahat.models import lugre
        >>> data = lugre.simulate(seed=0, t_end=0.2)
        >>> res = lugre.observer().run(data.t, data.u, 1e100 * data.y, throw=False)
        >>> res.status.name, res.failed_at, "t[0]" in res.message
        ('DIVERGED', 1, True)
        >>> bool(np.isnan(res.x_hat[1:]).all())            # the rows it could not compute
        True
        """
        if self.compiled is not False:
            plain = self.with_run_options(compiled=False)
            fast = runner(plain, t, compiled=self.compiled)
            return fast.run(t, u, y, state0=state0, throw=throw)
        t_, dts, U, Y, ok = self.check_records(t, u, y)
        s0 = self.init() if state0 is None else self.check_state(state0)
        N = t_.shape[0]
        check_allocation(8.0 * N * (2 * s0.size + 2 * self.layout.n), f"the estimates of {N} "
                         "samples", fix="run the record in pieces (pass the last state as "
                         "state0)")
        pert = self.system.require_perturbation("run")
        S = np.empty((N, s0.size))
        S[0] = s0
        fail: Failure | None = integrate_record(self.plan, pert, self.update_law, S, t_, dts,
                                                U[0], Y[0], ok[0], self.hold == "foh",
                                                self.progress)
        if fail is not None and throw:
            raise fail.error()
        return observer_result(pert, self.system.C, self.layout, t_, S, U[0], Y[0], ok[0],
                               fail)

    def __repr__(self) -> str:
        lay = self.layout
        return (f"ModifiedHighGainObserver(n={lay.n}, m={lay.m}, r={lay.r}, k={lay.k}, "
                f"p={lay.p}, "
                f"update_law={type(self.update_law).__name__}, "
                f"second={'None' if self.second is None else 'SecondObserver'}, "
                f"nan_policy={self.nan_policy!r}, hold={self.hold!r}"
                + ("" if self.compiled is False else f", compiled={self.compiled!r}") + ")")

