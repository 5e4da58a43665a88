"""Model-file studies: the plant of a model file, simulated for ε sweeps and (ε, Γ) tuning.

``thetahat sweep MODEL`` and ``thetahat tune MODEL`` run the file's
:class:`~thetahat.spec.EstimatorSpec` (:func:`~thetahat.modelfile.assembly.estimator_spec`)
on records simulated by :func:`simulate_model` from the file's ``[scenario]``: the system (1)
with the file's own g as the true perturbation, evaluated on the noise-free output C x, and
white noise on y. :func:`study_setup` gathers what such a study runs: the spec (with
``Gamma = "auto"`` and ``eps = "auto"`` chosen on the scenario's first record), the
simulator, θ̂(0), the state names, and a sentence on the experiment assumed when
``[scenario]`` does not define it.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..model.perturbation import Perturbation
from ..simulation.noise import Seed, WhiteNoise
from ..simulation.signals import FromArray, Multisine, time_grid
from ..simulation.simulate import PlantTrajectory, simulate_plant
from ..spec import EstimatorSpec
from .assembly import estimator_spec, resolve_gains
from .schema import ModelSpec

__all__ = ["EXPERIMENT_KEYS", "ModelPhi", "StudySetup", "simulate_model", "study_setup",
           "study_simulator"]

FloatArray = NDArray[np.float64]

#: The ``[scenario]`` keys that define the experiment (a study says which it assumed; the
#: integrator's settings are not announced).
EXPERIMENT_KEYS = ("theta", "u_amplitudes", "u_frequencies", "noise_std", "t_end", "fs")


@dataclass(frozen=True, slots=True, eq=False)
class ModelPhi:
    """The plant's φ = g(col(u, C x), x, θ) of a model file, with ∂φ/∂x.

    Call signature ``phi(t, x, u, theta)`` as :func:`~thetahat.simulation.simulate.
    simulate_plant` expects: ``x (..., n)``, ``u (..., m)`` (or None when m = 0),
    ``theta (..., p)``; returns ``(..., k)``.

    Parameters
    ----------
    perturbation : Perturbation
        The file's g(v, x, θ), v = col(u, y).
    C : ndarray, shape (r, n)
        The output matrix: y = C x (noise-free) inside the plant.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.modelfile.study import ModelPhi
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> phi = ModelPhi(perturbation=spec.system.perturbation, C=spec.system.C)
    >>> round(float(phi(0.0, [0.0, 1.0], [0.0], [1.0])[0]), 6)    # (2 + sin 0)(1 + 1/3)
    2.666667
    """

    perturbation: Perturbation
    C: FloatArray

    def _v(self, x: FloatArray, u: ArrayLike | None) -> FloatArray:
        y = x @ self.C.T
        u_ = np.zeros(y.shape[:-1] + (0,)) if u is None else np.asarray(u, dtype=np.float64)
        return np.concatenate([np.broadcast_to(u_, y.shape[:-1] + u_.shape[-1:]), y], axis=-1)

    def __call__(self, t: ArrayLike, x: ArrayLike, u: ArrayLike | None, theta: ArrayLike
                 ) -> FloatArray:
        """φ(x, u, θ); shape (..., k)."""
        x_ = np.asarray(x, dtype=np.float64)
        th = np.broadcast_to(np.asarray(theta, dtype=np.float64),
                             x_.shape[:-1] + np.shape(theta)[-1:])
        return np.asarray(self.perturbation.g(self._v(x_, u), x_, th), dtype=np.float64)

    def dphi_dx(self, t: ArrayLike, x: ArrayLike, u: ArrayLike | None, theta: ArrayLike
                ) -> FloatArray:
        """∂φ/∂x = ∂g/∂x + ∂g/∂y C; shape (..., k, n)."""
        x_ = np.asarray(x, dtype=np.float64)
        th = np.broadcast_to(np.asarray(theta, dtype=np.float64),
                             x_.shape[:-1] + np.shape(theta)[-1:])
        v = self._v(x_, u)
        r = self.C.shape[0]
        dv = np.asarray(self.perturbation.dg_dv(v, x_, th), dtype=np.float64)
        dx = np.asarray(self.perturbation.dg_dx(v, x_, th), dtype=np.float64)
        return dx + dv[..., v.shape[-1] - r:] @ self.C


def simulate_model(spec: ModelSpec, seed: Seed = 0, *, t_end: float | None = None
                   ) -> PlantTrajectory:
    """Simulate the plant of a model file for its ``[scenario]``, with seeded noise on y.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    seed : int or numpy.random.SeedSequence, optional
        Seed of the measurement noise.
    t_end : float, optional
        Overrides the scenario's duration (s).

    Returns
    -------
    PlantTrajectory
        ``t (N,)``, ``u (N, m)``, ``y (N, r)`` (noisy), the true ``x (N, n)``, ``phi (N, k)``
        and ``theta (p,)``.

    Raises
    ------
    SimulationError
        The integrator failed (try another ``method`` or smaller tolerances in
        ``[scenario]``).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.modelfile.study import simulate_model
    >>> data = simulate_model(loads_model(EXAMPLE_MODEL), seed=0, t_end=1.0)
    >>> data.x.shape, data.theta.tolist()
    ((101, 2), [1.0])
    """
    sc, s = spec.scenario, spec.system
    t_end = sc.t_end if t_end is None else t_end
    phi = ModelPhi(perturbation=cast(Perturbation, s.perturbation), C=s.C)
    u: Multisine | FromArray | None = (Multisine(sc.u_amplitudes, sc.u_frequencies) if s.m
                                       else None)
    if u is not None and sc.u_hold == "zoh":            # the sines' samples, held by a DAC
        t_k = time_grid(t_end, sc.fs)
        u = FromArray(t_k, u(t_k), hold="zoh")
    noise = WhiteNoise(sc.noise_std) if sc.noise_std > 0 else None
    return simulate_plant(s, phi=phi, dphi_dx=phi.dphi_dx, u=u, t_end=t_end, fs=sc.fs, x0=sc.x0,
                          theta=sc.theta, noise=noise, seed=seed, method=sc.method,
                          rtol=sc.rtol, atol=sc.atol)


def study_simulator(spec: ModelSpec, *, t_end: float | None = None
                    ) -> Callable[[int], PlantTrajectory]:
    """``simulate(seed)`` for :func:`~thetahat.studies.sweep.eps_sweep` and
    :func:`~thetahat.studies.tune.tune_eps_gamma` (picklable, for worker processes).

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    t_end : float, optional
        Overrides the scenario's duration (s).

    Returns
    -------
    callable
        ``simulate(seed) -> PlantTrajectory`` (:func:`simulate_model`).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.modelfile.study import study_simulator
    >>> study_simulator(loads_model(EXAMPLE_MODEL), t_end=1.0)(3).y.shape
    (101, 1)
    """
    return functools.partial(simulate_model, spec, t_end=t_end)


@dataclass(frozen=True, slots=True, eq=False)
class StudySetup:
    """What an ε sweep or an (ε, Γ) search of a model runs (``thetahat sweep``/``tune``).

    Attributes
    ----------
    estimator : EstimatorSpec
        The estimator, built for every ε and Γ from one SCB.
    simulate : callable
        ``simulate(seed) -> PlantTrajectory``, picklable.
    theta_hat0 : array_like, shape (p,)
        θ̂(0) of every run.
    state_names : tuple of str
        The n state names (the tables' labels).
    assumed : str or None
        A sentence naming the experiment keys the model does not give and the scenario
        assumed; None when it gives them all.
    """

    estimator: EstimatorSpec
    simulate: Callable[[int], PlantTrajectory]
    theta_hat0: Any
    state_names: tuple[str, ...]
    assumed: str | None = None

    def __repr__(self) -> str:
        return (f"StudySetup(estimator={self.estimator!r}, state_names={self.state_names}, "
                f"assumed={self.assumed is not None})")


def study_setup(spec: ModelSpec, *, t_end: float | None = None) -> StudySetup:
    """What ``thetahat sweep MODEL`` and ``thetahat tune MODEL`` run.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    t_end : float, optional
        Overrides the scenario's duration (s).

    Returns
    -------
    StudySetup
        The file's :class:`~thetahat.spec.EstimatorSpec` (``Gamma = "auto"`` and
        ``eps = "auto"``: chosen on the scenario's first record, seed 0, by
        :func:`~thetahat.modelfile.resolve_gains`), the
        simulator of :func:`study_simulator`, the file's θ̂(0) and state names, and which of
        :data:`EXPERIMENT_KEYS` the file left to their defaults.

    Raises
    ------
    ModelFileError, NotMinimumPhaseError, UnstableDesignError
        As for :func:`~thetahat.modelfile.estimator_spec`.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.modelfile.study import study_setup
    >>> setup = study_setup(loads_model(EXAMPLE_MODEL), t_end=1.0)
    >>> setup.state_names, setup.assumed.split(";")[0]
    (('x1', 'x2'), '<string> [scenario] gives no theta, u_amplitudes, u_frequencies, noise_std, t_end, fs')
    """
    chosen = [k for k in EXPERIMENT_KEYS if k in spec.scenario.defaults]
    assumed = (f"{spec.source} [scenario] gives no {', '.join(chosen)}; using "
               f"{spec.scenario!r}" if chosen else None)
    est, simulate = estimator_spec(spec), study_simulator(spec, t_end=t_end)
    if spec.estimator.gamma_auto or spec.estimator.eps_auto:    # chosen on the first record
        first = simulate(0)
        # a DAC in the experiment: the gains' statistical pass holds the samples as it does
        gains = resolve_gains(spec, first.t, first.u, first.y,
                              hold="zoh" if spec.scenario.u_hold == "zoh" else None)
        est = dataclasses.replace(est, eps=gains.eps)
        if spec.estimator.gamma_auto:
            est = dataclasses.replace(est, law=est.law_with_gamma(gains.Gamma))
    return StudySetup(estimator=est, simulate=simulate, theta_hat0=spec.estimator.theta_hat0,
                      state_names=spec.state_names, assumed=assumed)
