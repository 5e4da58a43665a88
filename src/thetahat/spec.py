"""One place to assemble an estimator: a frozen :class:`EstimatorSpec` and its ``build``.

An estimator of the paper is fixed by the system (1) (with g and Θ), the system the gains are
designed on (the true one, or a simplified design system, Sec. VII–VIII), ε and the poles of
the modified high-gain design (7), the update law (8), the optional second observer of
Sec. VI and the sample hold. :class:`EstimatorSpec` holds exactly that, designs the gains once
on construction, and ``build(eps=…, Gamma=…)`` returns the observer (3) for any ε and Γ:
K(ε) comes from :meth:`~thetahat.design.gains.GainDesign.at`, which reuses the SCB (only the
chain injection K'_qj = col(K̄_qj1/ε, …, K̄_qjn/ε^n) depends on ε, by the corrigendum), so an ε
sweep or an (ε, Γ) search costs one SCB. :func:`thetahat.models.lugre.estimator_spec`, model
files (:func:`thetahat.modelfile.estimator_spec`) and the ``thetahat`` command all build their
observers from here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from numpy.typing import ArrayLike

from .design.design_system import apply_design
from .design.gains import GainDesign, PoleSpec, check_eps, high_gain, modified_high_gain
from .errors import DimensionError, ThetahatError, UpdateLawError
from .estimation.observer.observer import ModifiedHighGainObserver
from .estimation.protocol import EstimateResult
from .estimation.observer.redesign import SecondObserver
from .estimation.observer.laws import UpdateLaw
from .model.system import PerturbedLinearSystem

__all__ = ["HOLDS", "SECOND_DESIGN_NOTE", "EstimatorSpec", "SecondObserverSpec"]

#: Sample holds of :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.run`.
HOLDS = ("zoh", "foh")

Hold = Literal["zoh", "foh"]

#: Note added to an error of the second observer's design (to tell it from the first's).
SECOND_DESIGN_NOTE = "in the second observer's high-gain design (EstimatorSpec.second)"


def _poles(value: PoleSpec) -> PoleSpec:
    """Pole lists as tuples (the spec is immutable); None and callables as they are."""
    if value is None or callable(value):
        return value
    return tuple(tuple(p) for p in value)


@dataclass(frozen=True, slots=True)
class SecondObserverSpec:
    """The second observer of Sec. VI: a high-gain observer that trusts θ̂.

    Parameters
    ----------
    eps2 : float, optional
        ε of its high-gain design :func:`~thetahat.design.gains.high_gain` (default 1).
    chain_poles : list of pole lists or callable, optional
        Poles of each H_j (default −1, −2, …).
    b_poles : sequence of complex, optional
        Poles of A_b − K_bb C_b (default −1, −2, …).
    g_on_estimates : bool, optional
        Evaluate g on C x̂₂ instead of the measured y (Sec. VIII); default False.

    Examples
    --------
    >>> from thetahat.spec import SecondObserverSpec
    >>> SecondObserverSpec(eps2=1.0, chain_poles=[[-1.0, -2.0]], g_on_estimates=True)
    SecondObserverSpec(eps2=1.0, chain_poles=((-1.0, -2.0),), b_poles=None, g_on_estimates=True)
    """

    eps2: float = 1.0
    chain_poles: PoleSpec = None
    b_poles: Sequence[complex] | None = None
    g_on_estimates: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "eps2", check_eps(self.eps2))
        object.__setattr__(self, "chain_poles", _poles(self.chain_poles))
        if self.b_poles is not None:
            object.__setattr__(self, "b_poles", tuple(self.b_poles))
        if not isinstance(self.g_on_estimates, bool):
            raise DimensionError(f"SecondObserverSpec.g_on_estimates must be True or False; "
                                 f"got {self.g_on_estimates!r}.")


@dataclass(frozen=True, slots=True, repr=False, eq=False)
class EstimatorSpec:
    """Everything that fixes an estimator of the paper; ``build`` makes the observer (3).

    The gains are designed once, on construction: K(ε) = [K_x; K_φ] by
    :func:`~thetahat.design.gains.modified_high_gain` on the design system (7), and the second
    observer's gain by :func:`~thetahat.design.gains.high_gain`.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The system (1) with its perturbation g and parameter set Θ.
    law : UpdateLaw
        The update law (8) (Propositions 1–4), with its Γ; ``build(Gamma=…)`` replaces Γ.
    eps : float, optional
        ε of the modified high-gain design (default 1, the start of Sec. VII).
    chain_poles : list of pole lists or callable, optional
        Poles of each H_j (default −1, −2, …; see :func:`~thetahat.design.gains.high_gain`).
    b_poles : sequence of complex, optional
        Poles of A_b − K_bb C_b.
    design_system : PerturbedLinearSystem, optional
        The system whose (A, E, C) the gains are designed on (Sec. VII–VIII); default: the
        true ``system``. Its B, g and Θ are not used.
    second : SecondObserverSpec, optional
        The second observer of Sec. VI (fills ``x_hat_refined``).
    hold : {"zoh", "foh"}, optional
        Sample hold used by :meth:`run`.
    nan_policy : {"raise", "skip"}, optional
        What the observer does with a NaN sample (see
        :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`).
    allow_nonminimum_phase : bool, optional
        Design and build even when Assumption 1 fails (zeros in the closed right half-plane)
        or when the gain leaves the true system unstable: only to study the failure.

    Attributes
    ----------
    design : GainDesign
        K(ε) at ``eps`` (its SCB is reused for every other ε).
    design2 : GainDesign or None
        The second observer's gain.

    Raises
    ------
    DimensionError
        The design system's sizes differ from the system's, or ``hold`` is unknown.
    DesignError
        The gains cannot be designed (wrong number of poles, ε ≤ 0, …).
    NotLeftInvertibleError
        Assumption 1 fails on the design system.
    NotMinimumPhaseError
        The design or the true system has zeros in the closed right half-plane (unless
        ``allow_nonminimum_phase``).
    UnstableDesignError
        A gain designed on the design system leaves the true error system unstable (unless
        ``allow_nonminimum_phase``).

    Examples
    --------
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.spec import EstimatorSpec
    >>> spec = EstimatorSpec(system=prop3_monotone.system(), law=prop3_monotone.update_law(),
    ...                      eps=0.5)
    >>> obs = spec.build(eps=0.1, Gamma=5.0)
    >>> obs.update_law.Gamma.tolist(), spec.design.at(0.1).K.shape
    ([[5.0]], (3, 1))
    >>> spec
    EstimatorSpec(law=GradientInversion, eps=0.5, Gamma=[2.0], design_system=False, second=False, hold='zoh')
    """

    system: PerturbedLinearSystem
    law: UpdateLaw
    eps: float = 1.0
    chain_poles: PoleSpec = None
    b_poles: Sequence[complex] | None = None
    design_system: PerturbedLinearSystem | None = None
    second: SecondObserverSpec | None = None
    hold: Hold = "zoh"
    nan_policy: str = "raise"
    allow_nonminimum_phase: bool = False
    design: GainDesign = field(init=False)
    design2: GainDesign | None = field(init=False)

    def __post_init__(self) -> None:
        if not isinstance(self.system, PerturbedLinearSystem):
            raise DimensionError(f"EstimatorSpec.system must be a PerturbedLinearSystem; got "
                                 f"{type(self.system).__name__}.")
        if not isinstance(self.law, UpdateLaw):
            raise UpdateLawError(f"EstimatorSpec.law must be an UpdateLaw (Propositions 1–4); "
                                 f"got {type(self.law).__name__}.")
        if self.hold not in HOLDS:
            raise DimensionError(f"EstimatorSpec.hold must be one of {HOLDS}; got "
                                 f"{self.hold!r}.")
        if self.second is not None and not isinstance(self.second, SecondObserverSpec):
            raise DimensionError(f"EstimatorSpec.second must be a SecondObserverSpec or None; "
                                 f"got {type(self.second).__name__}.")
        if self.design_system is not None and not isinstance(self.design_system,
                                                             PerturbedLinearSystem):
            raise DimensionError(f"EstimatorSpec.design_system must be a PerturbedLinearSystem "
                                 f"or None; got {type(self.design_system).__name__}.")
        ds = self.system if self.design_system is None else self.design_system
        if (ds.n, ds.r, ds.k) != (self.system.n, self.system.r, self.system.k):
            raise DimensionError(f"the design system has (n, r, k) = {(ds.n, ds.r, ds.k)} but "
                                 f"the system has {(self.system.n, self.system.r, self.system.k)}"
                                 f"; design on a system of the same sizes.")
        object.__setattr__(self, "eps", check_eps(self.eps))
        object.__setattr__(self, "chain_poles", _poles(self.chain_poles))
        if self.b_poles is not None:
            object.__setattr__(self, "b_poles", tuple(self.b_poles))
        allow = self.allow_nonminimum_phase
        object.__setattr__(self, "design", modified_high_gain(
            ds.A, ds.E, ds.C, self.eps, self.chain_poles, self.b_poles,
            allow_nonminimum_phase=allow))
        d2 = None
        if self.second is not None:
            s = self.second
            try:
                d2 = high_gain(ds.A, ds.E, ds.C, s.eps2, s.chain_poles, s.b_poles,
                               allow_nonminimum_phase=allow)
            except ThetahatError as exc:
                exc.add_note(SECOND_DESIGN_NOTE)
                raise
        object.__setattr__(self, "design2", d2)
        self.designs()                    # a design system's gains must hold on the true one

    def designs(self, eps: float | None = None) -> tuple[GainDesign, GainDesign | None]:
        """K(ε) of the observer (3) and the second observer's gain, without a new SCB.

        Parameters
        ----------
        eps : float, optional
            ε of the first design; default: the spec's.

        Returns
        -------
        design : GainDesign
            K(ε) = [K_x; K_φ] (:meth:`~thetahat.design.gains.GainDesign.at`).
        design2 : GainDesign or None
            The second observer's gain (independent of ``eps``).

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> d1, d2 = lugre.estimator_spec().designs(eps=0.5)
        >>> [round(float(v), 4) for v in d1.K.ravel()], d2.eps
        ([12.0, -0.0085, 12.0302], 1.0)
        """
        d1 = self.design.at(self.eps if eps is None else eps)
        if self.design_system is not None:
            A, E, C = self.system.A, self.system.E, self.system.C
            for d, note in ((d1, None), (self.design2, SECOND_DESIGN_NOTE)):
                if d is None:
                    continue
                try:
                    apply_design(d, A, E, C, allow_unstable=self.allow_nonminimum_phase)
                except ThetahatError as exc:
                    if note is not None:
                        exc.add_note(note)
                    raise
        return d1, self.design2

    def law_with_gamma(self, Gamma: ArrayLike) -> UpdateLaw:
        """The spec's update law with another adaptation gain Γ.

        Parameters
        ----------
        Gamma : float or array_like, shape (p, p)
            Symmetric positive-definite Γ (a number means Γ·I).

        Returns
        -------
        UpdateLaw
            A new law of the same kind and options.

        Raises
        ------
        UpdateLawError
            The law has no Γ (e.g. :class:`~thetahat.estimation.observer.laws.ConstantLaw`),
            or Γ is not symmetric positive definite.

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> lugre.estimator_spec().law_with_gamma(3.0).Gamma.tolist()
        [[3.0]]
        """
        names: set[str] = set()
        if dataclasses.is_dataclass(self.law):
            names = {f.name for f in dataclasses.fields(self.law)}
        if "Gamma" not in names:
            raise UpdateLawError(f"the update law {type(self.law).__name__} has no adaptation "
                                 f"gain Γ; leave Gamma unset.")
        return dataclasses.replace(self.law, Gamma=Gamma)  # type: ignore[type-var]

    def build(self, eps: float | None = None, Gamma: ArrayLike | None = None
              ) -> ModifiedHighGainObserver:
        """The observer (3) with K(ε) and the law with Γ; the spec's values by default.

        Parameters
        ----------
        eps : float, optional
            ε of K(ε) (0 < ε ≤ 1); reuses the spec's SCB.
        Gamma : float or array_like, shape (p, p), optional
            Adaptation gain Γ of the update law.

        Returns
        -------
        ModifiedHighGainObserver
            With the second observer when the spec has one, and the spec's hold.

        Raises
        ------
        DesignError
            ε ≤ 0.
        UpdateLawError
            Γ given for a law without Γ, or Γ not symmetric positive definite.

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> obs = lugre.estimator_spec().build(eps=0.5, Gamma=3.0)
        >>> obs.K_phi.round(4).tolist(), obs.update_law.Gamma.tolist()
        ([[12.0302]], [[3.0]])
        """
        d1, d2 = self.designs(eps)
        law = self.law if Gamma is None else self.law_with_gamma(Gamma)
        second = None
        if d2 is not None and self.second is not None:
            second = SecondObserver(system=self.system, K_x=d2.K,
                                    g_on_estimates=self.second.g_on_estimates)
        return ModifiedHighGainObserver(system=self.system, K_x=d1.K_x, K_phi=d1.K_phi,
                                        update_law=law, second=second,
                                        nan_policy=self.nan_policy, hold=self.hold,
                                        allow_nonminimum_phase=self.allow_nonminimum_phase)

    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            eps: float | None = None, Gamma: ArrayLike | None = None,
            x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None,
            progress: Callable[[int, int], None] | None = None) -> EstimateResult:
        """Build the observer and run it on sampled data with the spec's hold.

        Parameters
        ----------
        t : array_like, shape (N,)
            Strictly increasing sampling instants.
        u : array_like, shape (N, m), or None when m = 0
        y : array_like, shape (N, r)
        eps, Gamma : optional
            As in :meth:`build`.
        x_hat0 : array_like, shape (n,), optional
            Initial x̂ (default 0).
        theta_hat0 : array_like, shape (p,), optional
            Initial θ̂, in Θ (default: the law's, the centre of Θ for a box).
        progress : callable, optional
            ``progress(done, total)`` called as samples are processed (see
            :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.run`).

        Returns
        -------
        EstimateResult

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> data = lugre.simulate(seed=0, t_end=0.5)
        >>> res = lugre.estimator_spec().run(data.t, data.u, data.y, theta_hat0=[0.5])
        >>> res.theta_hat.shape
        (501, 1)
        """
        obs = self.build(eps, Gamma).with_run_options(progress=progress)
        state0 = obs.init(x_hat0=x_hat0, theta_hat0=theta_hat0)
        return obs.run(t, u, y, state0=state0)

    def __repr__(self) -> str:
        gamma = getattr(self.law, "Gamma", None)
        g = "-" if gamma is None else (gamma.ravel().tolist() if gamma.size > 1 else
                                       [float(gamma.ravel()[0])])
        return (f"EstimatorSpec(law={type(self.law).__name__}, eps={self.eps:g}, Gamma={g}, "
                f"design_system={self.design_system is not None}, "
                f"second={self.second is not None}, hold={self.hold!r})")

