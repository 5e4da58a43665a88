"""Model-file assembly: the estimator a :class:`~thetahat.modelfile.schema.ModelSpec` describes.

From a spec read by :func:`~thetahat.modelfile.schema.load_model`: its
:class:`~thetahat.spec.EstimatorSpec` (the gain designs on the design system, the update law,
the second observer, the hold), the observer (3) it builds, and a run on sampled data. All
assembly happens in :mod:`thetahat.spec`; this module only maps the file's keys onto it and
names the keys in its error messages.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_samples, seconds_from_first
from ..design.gains import GainDesign
from ..errors import (ConvergenceWarning, DesignError, ModelFileError, NonFiniteError,
                      NotMinimumPhaseError, ThetahatError, ThetahatWarning, UnstableDesignError)
from ..estimation.hold import DEFAULT_HOLD
from ..estimation.observer.auto_eps import EpsChoice
from ..estimation.observer.checks import check_theta_star
from ..estimation.observer.initial_state import x_hat_from_output
from ..estimation.observer.laws.projection import as_gain
from ..estimation.observer.observer import ModifiedHighGainObserver
from ..estimation.protocol import EstimateResult, Estimator
from ..methods import MethodInputs, get_method
from ..model.state_set import measured_states
from ..model.system import PerturbedLinearSystem
from ..progress import FitProgress, Stages
from ..spec import SECOND_DESIGN_NOTE, EstimatorSpec, Hold, SecondObserverSpec
from ..studies.information import explain_nonfinite, stuck_parameters
from ..threads import one_blas_thread
from .holds import split_hold
from .schema import ModelSpec

if TYPE_CHECKING:
    from ..estimation.statistical.map_fit import FitResult
    from ..estimation.statistical.trust import TrustReport

__all__ = ["ObserverGains", "auto_eps", "auto_gamma", "build_estimator", "build_observer",
           "design_gains", "design_matrices", "estimator_spec", "held_run", "resolve_gains",
           "run_estimator", "start_x_hat"]

FloatArray = NDArray[np.float64]


def design_matrices(spec: ModelSpec) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(A, E, C) of the system the gains are designed on: the design system if the file has one.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.

    Returns
    -------
    A, E, C : ndarray
        Shapes (n, n), (n, k), (r, n).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, design_matrices, loads_model
    >>> [a.shape for a in design_matrices(loads_model(EXAMPLE_MODEL))]
    [(2, 2), (2, 1), (1, 2)]
    """
    s, est = spec.system, spec.estimator
    return (s.A if est.A_design is None else est.A_design,
            s.E if est.E_design is None else est.E_design, s.C)


def estimator_spec(spec: ModelSpec, *, hold: Hold = "zoh",
                   nan_policy: str = "raise") -> EstimatorSpec:
    """The :class:`~thetahat.spec.EstimatorSpec` of a model file (gains designed once).

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    hold : {"zoh", "foh"}, optional
        Sample hold of :meth:`~thetahat.spec.EstimatorSpec.run`.
    nan_policy : {"raise", "skip"}, optional
        What the observer does with a NaN sample (a dropout).

    Returns
    -------
    EstimatorSpec
        ``build(eps=…, Gamma=…)`` gives the file's observer for any ε and Γ.

    Raises
    ------
    ModelFileError
        A design failed (e.g. a wrong number of chain poles, Assumption 1 fails on the design
        system); the message names the keys.
    NotMinimumPhaseError
        Assumption 1 fails on the design system (unless ``allow_nonminimum_phase = true``).
    UnstableDesignError
        The gains designed on the design system leave the true system unstable (unless
        ``allow_nonminimum_phase = true``).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, estimator_spec, loads_model
    >>> est = estimator_spec(loads_model(EXAMPLE_MODEL))
    >>> est
    EstimatorSpec(law=GradientInversion, eps=0.5, Gamma=[2.0], design_system=False, second=True, hold='zoh')
    >>> est.build(eps=0.25).K_phi.round(3).tolist()
    [[496.0]]
    """
    est, s = spec.estimator, spec.system
    has_design = est.A_design is not None or est.E_design is not None
    where = "the design system (A_design, E_design)" if has_design else "(A, E, C)"
    second = None
    if est.second is not None:
        second = SecondObserverSpec(eps2=est.second.eps2, chain_poles=est.second.chain_poles,
                                    b_poles=est.second.b_poles,
                                    g_on_estimates=est.second.g_on_estimates)
    design_system = None
    if has_design:
        A_d, E_d, C = design_matrices(spec)
        design_system = PerturbedLinearSystem(A=A_d, B=s.B, C=C, E=E_d)
    try:
        return EstimatorSpec(system=s, law=est.update_law, eps=est.eps,
                             chain_poles=est.chain_poles, b_poles=est.b_poles,
                             design_system=design_system, second=second, hold=hold,
                             nan_policy=nan_policy,
                             allow_nonminimum_phase=est.allow_nonminimum_phase)
    except NotMinimumPhaseError as exc:
        raise NotMinimumPhaseError(f"model file {spec.source}: Assumption 1 fails on {where}: "
                                   f"{exc} (or set allow_nonminimum_phase = true in "
                                   f"[estimator] to design anyway).", zeros=exc.zeros) from exc
    except UnstableDesignError as exc:
        name = ("[estimator.second]" if SECOND_DESIGN_NOTE in getattr(exc, "__notes__", ())
                else "[estimator]")
        raise UnstableDesignError(f"model file {spec.source}: {name}: {exc}",
                                  eigenvalues=exc.eigenvalues) from exc
    except ThetahatError as exc:
        if SECOND_DESIGN_NOTE in getattr(exc, "__notes__", ()):
            raise ModelFileError(f"model file {spec.source}: [estimator.second]: the "
                                 f"high-gain design on {where} failed: {exc}") from exc
        raise ModelFileError(f"model file {spec.source}: [estimator] eps/chain_poles/b_poles: "
                             f"the modified high-gain design on {where} failed: {exc}") from exc


def design_gains(spec: ModelSpec, eps: float | None) -> tuple[GainDesign, GainDesign | None]:
    """K(ε) of the modified high-gain observer and, if any, the second observer's gain.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    eps : float or None
        Overrides ``spec.estimator.eps``.

    Returns
    -------
    design : GainDesign
        K(ε) = [K_x; K_φ].
    design2 : GainDesign or None
        The second observer's gain.

    Raises
    ------
    ModelFileError
        A design failed; the message names the keys.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, design_gains, loads_model
    >>> d1, d2 = design_gains(loads_model(EXAMPLE_MODEL), None)
    >>> d1.eps, d2.eps
    (0.5, 1.0)
    """
    return estimator_spec(spec).designs(eps)


def build_observer(spec: ModelSpec, *, eps: float | None = None,
                   Gamma: ArrayLike | None = None,
                   nan_policy: str = "raise") -> ModifiedHighGainObserver:
    """The estimator of a model file: observer (3) with the file's update law (8).

    Built by :meth:`~thetahat.spec.EstimatorSpec.build` from :func:`estimator_spec`: the
    gains K(ε) = [K_x; K_φ] are designed by :func:`~thetahat.design.gains.modified_high_gain`
    on the design system (or the true one), and the second observer's, if any, by
    :func:`~thetahat.design.gains.high_gain`.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`load_model`.
    eps : float, optional
        Overrides ``spec.estimator.eps``; needed when the file says ``eps = "auto"``
        (:func:`resolve_gains` chooses it on a record).
    Gamma : float or array_like, shape (p, p), optional
        Γ of the update law in place of the file's; needed when the file says ``"auto"``
        (:func:`resolve_gains` chooses it on a record, as :func:`run_estimator` does).
    nan_policy : {"raise", "skip"}, optional
        What the observer does with a NaN sample (a dropout).

    Returns
    -------
    ModifiedHighGainObserver
        Start it with ``init(x_hat0=spec.estimator.x_hat0,
        theta_hat0=spec.estimator.theta_hat0)``, or use :func:`run_estimator`.

    Raises
    ------
    ModelFileError
        The gains cannot be designed (e.g. a wrong number of chain poles, Assumption 1
        fails on the design system); the message names the keys. Or Γ is ``"auto"`` and no
        ``Gamma`` is given: it is chosen on a record (:func:`resolve_gains`).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> obs = build_observer(loads_model(EXAMPLE_MODEL))
    >>> obs.K_x.shape, obs.K_phi.shape
    ((2, 1), (1, 1))
    """
    if Gamma is None:
        _refuse_auto_gamma(spec)
    else:
        Gamma = resolve_gains(spec, eps=eps, Gamma=Gamma).Gamma
    if eps is None:
        _refuse_auto_eps(spec)
    return _build(estimator_spec(spec, nan_policy=nan_policy), spec, eps, Gamma=Gamma)


def _refuse_auto_gamma(spec: ModelSpec) -> None:
    """``Gamma = "auto"`` is chosen on a record: refused where there is none."""
    if spec.estimator.gamma_auto:
        raise _no_record(spec)


def _refuse_auto_eps(spec: ModelSpec) -> None:
    """``eps = "auto"`` is chosen on a record: refused where there is none."""
    if spec.estimator.eps_auto:
        raise _no_record(spec, "eps")


def _no_record(spec: ModelSpec, key: str = "Gamma") -> ModelFileError:
    if key == "eps":
        return ModelFileError(
            f"model file {spec.source}: [estimator] eps = 'auto' is chosen on a record, and "
            "there is none here. Choose it on your log as the estimate does (thetahat codegen "
            "--data LOG; resolve_gains(spec, t, u, y)), give the ε that thetahat estimate "
            "printed for it (thetahat codegen --eps E; eps=), or set eps in [estimator] (a "
            "number > 0).")
    return ModelFileError(
            f"model file {spec.source}: [estimator] Gamma = 'auto' (the default of the "
            "gradient and least-squares laws) is chosen on a record, and there is none here. "
            "Choose it on your log as the estimate does (thetahat codegen --data LOG; "
            "resolve_gains(spec, t, u, y)), give the Γ that thetahat estimate printed for it "
            "(thetahat codegen --gamma G...; Gamma=), or set Gamma in [estimator] (a number "
            "or a p × p matrix).")


@dataclass(frozen=True, slots=True, eq=False)
class ObserverGains:
    """The ε and Γ a model file's observer runs with, resolved (:func:`resolve_gains`).

    Attributes
    ----------
    eps : float
        ε of K(ε): the file's ``[estimator] eps``, chosen on a record (``eps = "auto"``,
        :func:`auto_eps`) or the caller's.
    Gamma : ndarray, shape (p, p)
        Γ of the update law, symmetric positive definite (read-only).
    source : {"file", "auto", "given"}
        Where Γ came from: the file's number or matrix, ``Gamma = "auto"`` chosen on a record
        (:func:`auto_gamma`), or the caller's (``thetahat codegen --gamma``).
    eps_source : {"file", "auto", "given"}
        Where ε came from, likewise.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import ObserverGains
    >>> g = ObserverGains(eps=0.025, Gamma=np.diag([1500.0, 2.5]), source="auto")
    >>> print(g)
    observer gains: eps = 0.025, Gamma = diag(1500, 2.5) ("auto", chosen on this record; for C: thetahat codegen MODEL --eps 0.025 --gamma 1500 2.5)
    >>> g.options
    '--eps 0.025 --gamma 1500 2.5'
    """

    eps: float
    Gamma: FloatArray
    source: str
    eps_source: str = "file"

    def __post_init__(self) -> None:
        if self.Gamma.flags.writeable:
            self.Gamma.setflags(write=False)

    @property
    def options(self) -> str:
        """The ``thetahat codegen`` options that build this observer (``--gamma`` takes Γ's
        diagonal; a Γ with off-diagonal terms has no option, ``Gamma`` in the file then)."""
        G = self.Gamma
        eps = f"--eps {self.eps:.6g}"
        if np.count_nonzero(G - np.diag(np.diag(G))):
            return eps
        d = np.diag(G)
        diag = [d[0]] if np.all(d == d[0]) else list(d)
        return eps + " --gamma " + " ".join(f"{g:.6g}" for g in diag)

    def __str__(self) -> str:
        G = self.Gamma
        d = np.diag(G)
        if np.count_nonzero(G - np.diag(d)):
            shown = "[" + ", ".join("[" + ", ".join(f"{v:.6g}" for v in row) + "]"
                                    for row in G) + "]"
        elif np.all(d == d[0]):
            shown = f"{d[0]:.6g}"
        else:
            shown = "diag(" + ", ".join(f"{v:.6g}" for v in d) + ")"
        why = {"file": "the model file's", "given": "given",
               "auto": '"auto", chosen on this record'}[self.source]
        if "auto" in (self.source, self.eps_source):
            why += f"; for C: thetahat codegen MODEL {self.options}"
        eps_why = ' ("auto", chosen on this record)' if self.eps_source == "auto" else ""
        return f"observer gains: eps = {self.eps:.6g}{eps_why}, Gamma = {shown} ({why})"

    def __repr__(self) -> str:
        return (f"ObserverGains(eps={self.eps:.6g}, Gamma={np.round(self.Gamma, 6).tolist()}, "
                f"source={self.source!r}, eps_source={self.eps_source!r})")


def resolve_gains(spec: ModelSpec, t: ArrayLike | None = None, u: ArrayLike | None = None,
                  y: ArrayLike | None = None, *, eps: float | None = None,
                  Gamma: ArrayLike | None = None, hold: str | None = None,
                  nan_policy: str = "raise") -> ObserverGains:
    """The ε and Γ the file's observer runs with: ``"auto"`` ones chosen on a record.

    The one place where ``"auto"`` becomes a number (ε first, by :func:`auto_eps`, then Γ by
    :func:`auto_gamma` with that ε): :func:`run_estimator` (``thetahat
    estimate``, which prints the result) and ``thetahat codegen --data LOG`` call it, so a C
    observer generated from the same log runs with the Γ the estimate used.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    t, u, y : array_like, optional
        A record, as for :func:`run_estimator`; needed only when the file says
        ``Gamma = "auto"`` or ``eps = "auto"`` and no ``Gamma`` or ``eps`` is given.
    eps : float, optional
        Overrides ``[estimator] eps`` (also for the first pass of ``Gamma = "auto"``).
    Gamma : float or array_like, optional
        Γ itself, in place of the file's: a number (γI), p numbers (the diagonal) or a
        p × p matrix.
    hold : {"zoh", "foh", "bandlimited", "smooth"}, optional
        The run's hold; the first pass of ``"auto"`` takes the observer's
        (:func:`~thetahat.modelfile.holds.split_hold`).
    nan_policy : {"raise", "skip"}
        Missing outputs in the record of ``"auto"``: refused, or predicted over by the first
        pass (as the run that follows does) and left out of the information.

    Returns
    -------
    ObserverGains

    Raises
    ------
    ModelFileError
        ``Gamma = "auto"`` with neither a record nor ``Gamma``, or ``eps = "auto"`` with
        neither a record nor ``eps`` (the message says how to give one).
    UpdateLawError
        ``Gamma`` is not positive definite or has the wrong size.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model, resolve_gains
    >>> spec = loads_model(EXAMPLE_MODEL)                 # Gamma = 2.0, eps = 0.5
    >>> print(resolve_gains(spec))
    observer gains: eps = 0.5, Gamma = 2 (the model file's)
    >>> auto = loads_model(EXAMPLE_MODEL.replace("Gamma = 2.0", 'Gamma = "auto"'))
    >>> t = np.arange(0.0, 5.0, 0.01)
    >>> resolve_gains(auto, t, np.sin(t)[:, None], np.sin(t)[:, None]).source
    'auto'
    """
    p = len(spec.parameter_names)
    record = t is not None and y is not None
    if record:
        t = as_samples("t", seconds_from_first("t", t))
        u = None if u is None else as_samples("u", u)
        y = as_samples("y", y)
    observer_hold = split_hold(hold, "guarded")[0]
    if eps is not None:
        eps, eps_source = float(eps), "given"
    elif spec.estimator.eps_auto:
        if not record:
            raise _no_record(spec, "eps")
        eps, eps_source = auto_eps(spec, t, u, y, hold=observer_hold,    # type: ignore[arg-type]
                                   nan_policy=nan_policy).eps, "auto"
    else:
        eps, eps_source = spec.estimator.eps, "file"
    if Gamma is not None:
        G = np.asarray(Gamma, dtype=np.float64)
        if G.ndim == 1 and G.size == p and p > 1:
            G = np.diag(G)
        elif G.ndim == 1 and G.size == 1:
            G = G.reshape(())
        return ObserverGains(eps=eps, Gamma=as_gain("Gamma", G, p), source="given",
                             eps_source=eps_source)
    if not spec.estimator.gamma_auto:
        law_gamma = getattr(spec.estimator.update_law, "Gamma", None)
        G = np.eye(p) if law_gamma is None else np.array(law_gamma, dtype=np.float64)
        return ObserverGains(eps=eps, Gamma=G, source="file", eps_source=eps_source)
    if not record:
        raise _no_record(spec)
    G = auto_gamma(spec, t, u, y, hold=observer_hold, eps=eps,     # type: ignore[arg-type]
                   nan_policy=nan_policy)
    return ObserverGains(eps=eps, Gamma=G, source="auto", eps_source=eps_source)


def _build(est: EstimatorSpec, spec: ModelSpec, eps: float | None,
           Gamma: FloatArray | None = None) -> ModifiedHighGainObserver:
    try:
        return est.build(eps, Gamma=Gamma)
    except NotMinimumPhaseError as exc:
        raise NotMinimumPhaseError(
            f"model file {spec.source}: Assumption 1 fails on the true system: {exc} (or "
            f"set allow_nonminimum_phase = true in [estimator] to run anyway).",
            zeros=exc.zeros) from exc


def build_estimator(spec: ModelSpec, *, method: str | None = None, hold: str | None = None,
                    nan_policy: str = "raise", compiled: bool | None = None,
                    progress: Callable[[int, int], None] | None = None,
                    Gamma: FloatArray | None = None, noise_std: ArrayLike | None = None,
                    window: int | str | None = None, eps: float | None = None) -> Estimator:
    """The estimator a model file describes, by method, behind the one estimator protocol.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    method : str, optional
        One of :data:`thetahat.methods.ESTIMATION_METHODS` (default: the file's
        ``[estimator] method``): the paper's observer, the two-stage guarded estimator (that
        observer as stage 1), the MAP fits or the joint EKF.
    hold : {"zoh", "foh", "bandlimited", "smooth"}, optional
        u between the samples (:func:`~thetahat.modelfile.holds.split_hold`): default, the
        observer holds the samples (its ``step`` always does) and the statistical methods
        take ``"smooth"`` (u linear between samples corrected for a smooth input).
    nan_policy : {"raise", "skip"}
        What the observer does with a NaN sample (a dropout).
    compiled : bool, optional
        numba kernels for the statistical methods (default: when installed).
    progress : callable, optional
        ``progress(done, total)`` for the observer's ``run``.
    Gamma : ndarray (p, p), optional
        The observer's Γ in place of the file's (:func:`run_estimator` passes the Γ of
        ``Gamma = "auto"``, computed on the record).
    noise_std : float or array_like (r,), optional
        σ of the output noise for the statistical methods (default: estimated from the data,
        which needs 12 samples).
    window : {None, "auto"} or int, optional
        Bounded fits for ``guarded`` and ``mle``
        (:mod:`~thetahat.estimation.statistical.window`; default: fits of all the data).
    eps : float, optional
        The observer's ε in place of the file's (:func:`run_estimator` passes the ε of
        ``eps = "auto"``, chosen on the record).

    Returns
    -------
    Estimator
        Start it with ``init(x_hat0=spec.estimator.x_hat0,
        theta_hat0=spec.estimator.theta_hat0)``.

    Raises
    ------
    OptionError
        Unknown ``method``.
    ModelFileError
        ``Gamma = "auto"`` in the file and no ``Gamma`` given (it is chosen on a record:
        :func:`auto_gamma`).
    NotMinimumPhaseError, UnstableDesignError
        As for :func:`build_observer` (the observer's methods).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_estimator, loads_model
    >>> from thetahat.estimation.protocol import Estimator
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> from thetahat.methods import ESTIMATION_METHODS
    >>> all(isinstance(build_estimator(spec, method=m), Estimator) for m in ESTIMATION_METHODS)
    True
    """
    how = get_method(spec.estimator.method if method is None else method)
    observer_hold, stage2_hold = split_hold(hold, how.name)

    def observer() -> Estimator:
        if Gamma is None:
            _refuse_auto_gamma(spec)
        if eps is None:
            _refuse_auto_eps(spec)
        return _build(estimator_spec(spec, hold=observer_hold, nan_policy=nan_policy), spec,
                      eps, Gamma=Gamma).with_run_options(progress=progress, compiled=compiled)

    return how.build(MethodInputs(system=spec.system, observer=observer, compiled=compiled,
                                  noise_std=noise_std, hold=stage2_hold, window=window))


def run_estimator(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
                  hold: str | None = None, nan_policy: str = "raise",
                  progress: Callable[[int, int], None] | None = None,
                  method: str | None = None, compiled: bool | None = None,
                  diagnose: bool = True, Gamma: ArrayLike | None = None,
                  noise_std: ArrayLike | None = None,
                  fit_progress: FitProgress | None = None,
                  window: int | str | None = None,
                  eps: float | None = None) -> EstimateResult:
    """Run the file's estimator on sampled data, from the file's initial values.

    ``method`` (default: the file's ``[estimator] method``, else ``"guarded"``) chooses the
    paper's observer, the guarded two-stage estimator (that observer as stage 1), the
    offline MAP fits or the joint EKF (:func:`build_estimator`); every one returns an
    :class:`~thetahat.estimation.protocol.EstimateResult` with its own ``diagnostics``.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    t : array_like, shape (N,)
        Strictly increasing sampling instants.
    u : array_like, shape (N, m), or None when m = 0
        Input samples.
    y : array_like, shape (N, r)
        Output samples.
    hold : {"zoh", "foh", "bandlimited", "smooth"}, optional
        u between the samples, for every method
        (:func:`~thetahat.modelfile.holds.split_hold`; the trust report takes the statistical
        methods' one). Default: the observer holds the samples, the statistical methods take
        ``"smooth"`` (u linear between samples corrected for a smooth input).
    nan_policy : {"raise", "skip"}
        What the observer does with a NaN sample (a dropout).
    progress : callable or Stages, optional
        ``progress(done, total)`` called as samples are processed (the observer's methods).
        A :class:`thetahat.progress.Stages` counts them in its current stage, and the trust
        report (``diagnose``) is a stage of its own, ``"trust report"``; so are the fits of
        ``"guarded"`` and ``"mle"``, ``"fits"`` (:meth:`~thetahat.progress.Stages.fit_stage`),
        unless ``fit_progress`` is given.
    method : str, optional
        The estimator, one of :data:`thetahat.methods.ESTIMATION_METHODS` (default: the
        file's ``[estimator] method``).
    compiled : bool, optional
        numba kernels (default: when installed; for the paper's observer, on records of at
        least :data:`~thetahat.estimation.drive.COMPILE_MIN_SAMPLES` samples, see
        :func:`~thetahat.estimation.drive.runner`). A part the kernel does not support
        falls back to Python with a one-line ThetahatWarning.
    diagnose : bool
        Check the result (:func:`~thetahat.estimation.statistical.trust.trust_report`: the
        Cramér–Rao standard deviation of each parameter on this record, Θ's boundary, the
        guard's band, the model error) into ``result.trust``, and warn of what makes it less
        than trustworthy (:class:`~thetahat.errors.ThetahatWarning`; a
        :class:`~thetahat.errors.ConvergenceWarning` when no information reached the update
        law for a parameter, :func:`~thetahat.studies.information.stuck_parameters`). A run
        that fails is diagnosed too: the error names g undefined on the data, or the data's
        scale (:func:`~thetahat.studies.information.explain_nonfinite`).
    Gamma : float or array_like, optional
        Γ of the observer's law in place of the file's (as for :func:`resolve_gains`; pass
        ``resolve_gains(spec, t, u, y).Gamma`` to know the Γ of ``"auto"`` and run with it
        without choosing it twice, as ``thetahat estimate`` does).
    noise_std : float or array_like (r,), optional
        σ of the output noise, for the statistical methods and the trust report (default:
        estimated from the record, which needs 12 samples; ``thetahat estimate
        --noise-std``).
    fit_progress : callable, optional
        ``fit_progress(done, total)`` (:data:`thetahat.progress.FitProgress`) for the methods
        that fit (``"guarded"``, ``"mle"``: their ``run``'s keyword, called before the first
        fit and after each, ``total`` known in advance, the last call ``(total, total)``);
        the other methods make no fits and never call it. Its exceptions propagate unchanged.
    window : {None, "auto"} or int, optional
        Bounded fits for ``guarded`` and ``mle``: each fit past W samples covers the samples
        since the previous one, the EKF's posterior its arrival cost
        (:mod:`~thetahat.estimation.statistical.window`); None (default) fits all the data so
        far. The other methods ignore it.
    eps : float, optional
        ε of the observer in place of the file's (``eps = "auto"``: chosen on the record by
        :func:`auto_eps` unless given; :func:`resolve_gains` tells which).

    Returns
    -------
    EstimateResult
        With ``names``: the file's names of the states, parameters, inputs and outputs.

    Notes
    -----
    The run holds the BLAS libraries to one thread (:func:`thetahat.threads.one_blas_thread`,
    with threadpoolctl when installed): thetahat's matrices are small, and BLAS threads
    spinning on busy cores made the NumPy gradient law's per-sample ``expm`` 3–4× slower.

    Raises
    ------
    UpdateLawError
        The law's θ* is singular, or misses Θ, on this record (checked before estimation;
        the message names the instants).
    NotMinimumPhaseError, UnstableDesignError
        As for :func:`build_observer`.
    NonFiniteError, SimulationError
        The run failed numerically; the message says why when the data show it (g undefined
        on the data, the data's scale).
    OptionError
        Unknown ``method``.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model, run_estimator
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 1.0, 0.01)
    >>> y = 1e-3 * np.random.default_rng(0).standard_normal((t.size, 1))   # noise only
    >>> res = run_estimator(spec, t, np.sin(t)[:, None], y)
    >>> res.theta_hat.shape, res.names.states
    ((100, 1), ('x1', 'x2'))
    """
    with one_blas_thread():
        return _run(spec, t, u, y, hold=hold, nan_policy=nan_policy, progress=progress,
                    method=method, compiled=compiled, diagnose=diagnose, Gamma=Gamma,
                    noise_std=noise_std, fit_progress=fit_progress, window=window, eps=eps)


def _run(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
         hold: str | None,
         nan_policy: str, progress: Callable[[int, int], None] | None, method: str | None,
         compiled: bool | None, diagnose: bool, Gamma: ArrayLike | None,
         noise_std: ArrayLike | None, fit_progress: FitProgress | None,
         window: int | str | None, eps: float | None = None) -> EstimateResult:
    """:func:`run_estimator`'s work."""
    how = get_method(spec.estimator.method if method is None else method)
    observer_hold, stage2_hold = split_hold(hold, how.name)
    if fit_progress is None and isinstance(progress, Stages):
        fit_progress = progress.fit_stage("fits")
    # every method sees the same samples: masked entries as NaN, dates as seconds, booleans,
    # text and dates in u or y refused
    t = as_samples("t", seconds_from_first("t", t))
    u = None if u is None else as_samples("u", u)
    y = as_samples("y", y)
    x0, th0 = start_x_hat(spec, y), spec.estimator.theta_hat0
    if noise_std is not None:           # checked once (finite, > 0, one or r values)
        from ..estimation.statistical.common import resolve_noise_std
        noise_std = resolve_noise_std(noise_std, np.zeros((1, spec.system.r)))
    try:
        gamma = None
        if how.runs_observer:
            _check_theta_star(spec, t, u, y)
            if (Gamma is not None or spec.estimator.gamma_auto
                    or (eps is None and spec.estimator.eps_auto)):
                gains = resolve_gains(spec, t, u, y, eps=eps, Gamma=Gamma, hold=observer_hold,
                                      nan_policy=nan_policy)
                gamma, eps = gains.Gamma, gains.eps
        est = build_estimator(spec, method=how.name, hold=hold, nan_policy=nan_policy,
                              compiled=compiled, progress=progress, Gamma=gamma,
                              noise_std=noise_std, window=window, eps=eps)
        state0 = est.init(x_hat0=x0, theta_hat0=th0)
        if how.fits and fit_progress is not None:   # guarded's and mle's run take it
            fitting: Any = est
            result = fitting.run(t, u, y, state0=state0, fit_progress=fit_progress)
        else:
            result = est.run(t, u, y, state0=state0)
    except (ThetahatError, ArithmeticError, ValueError) as exc:       # LinAlgError too
        if not diagnose:
            raise
        err = explain_nonfinite(exc, spec.system, t, u, y, x0, th0)
        if err is exc:
            raise
        raise err from exc
    result = dataclasses.replace(result, names=spec.signal_names)
    if not diagnose:
        return result
    if isinstance(progress, Stages):
        progress.stage("trust report")
    fits = "none" if not how.fits else "record" if window is None else "window"
    report = _trust(spec, result, u, y, compiled, x0, noise_std, stage2_hold or DEFAULT_HOLD,
                    fits)
    for text in report.warnings:
        warnings.warn(text, ThetahatWarning, stacklevel=3)
    if spec.state_set is not None:
        outside = spec.state_set.leaving(measured_states(spec.system.C, y), spec.state_names)
        if outside:
            warnings.warn(outside, ThetahatWarning, stacklevel=3)
    stuck = stuck_parameters(spec.system, u, y, result.x_hat, result.theta_hat,
                             spec.parameter_names)
    if stuck:
        warnings.warn(stuck, ConvergenceWarning, stacklevel=3)
    return dataclasses.replace(result, trust=report)


def start_x_hat(spec: ModelSpec, y: ArrayLike) -> FloatArray:
    """x̂(0) of a model file's estimators on a record: x̂₀ + C⁺(y(0) − C x̂₀), or x̂₀.

    :func:`~thetahat.estimation.observer.initial_state.x_hat_from_output` of the first sample with the
    file's ``x_hat0`` as the prior, unless the file sets ``x_hat0_from_y = false``. Every
    method, :func:`run_estimator`, ``thetahat estimate`` and ``fleet`` and the generated C
    harness start there.

    Parameters
    ----------
    spec : ModelSpec
    y : array_like, shape (N, r)
        The record's outputs (only y(0) is read).

    Returns
    -------
    ndarray, shape (n,)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model, start_x_hat
    >>> spec = loads_model(EXAMPLE_MODEL)                   # C = [1, 0], x_hat0 = 0
    >>> start_x_hat(spec, np.array([[0.3], [0.4]])).tolist()
    [0.3, 0.0]
    """
    est = spec.estimator
    if not est.x_hat0_from_y:
        return np.array(est.x_hat0, dtype=np.float64)
    C = spec.system.C
    Y = np.asarray(y, dtype=np.float64).reshape(-1, C.shape[0])
    return x_hat_from_output(C, Y[0], est.x_hat0)


def auto_gamma(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
               hold: Hold = "zoh", eps: float | None = None,
               nan_policy: str = "raise") -> FloatArray:
    """``Gamma = "auto"`` on a record: the law's Γ (Γ₀) from the record's information.

    x̂ from a first pass of the file's observer with θ̂ held at θ̂₀, then
    :func:`~thetahat.estimation.observer.auto_gain.information_gain` at θ̂₀ with the law's κ
    (:func:`~thetahat.estimation.observer.auto_gain.auto_kappa`).

    Parameters
    ----------
    spec : ModelSpec
        With a gradient or least-squares law.
    t, u, y : array_like
        The record, as for :func:`run_estimator`.
    hold : {"zoh", "foh"}
    eps : float, optional
        ε of the first pass's observer (default the file's).
    nan_policy : {"raise", "skip"}
        As for :func:`run_estimator`: with ``"skip"`` the first pass predicts over missing
        outputs and their samples are left out of the information.

    Returns
    -------
    ndarray (p, p)
        Diagonal, positive definite.

    Raises
    ------
    ModelFileError
        The model has no perturbation or parameter set.
    UpdateLawError
        ∂g/∂θ vanishes on the whole record for a parameter.
    NonFiniteError
        The first pass stopped within two samples (a first pass that stops later gives Γ
        from the samples before, with a ThetahatWarning).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, auto_gamma, loads_model
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 5.0, 0.01)
    >>> G = auto_gamma(spec, t, np.sin(t)[:, None], np.sin(t)[:, None])
    >>> G.shape, bool(G[0, 0] > 0)
    ((1, 1), True)
    """
    from ..estimation.observer.auto_gain import auto_kappa, information_gain
    s = spec.system
    th0 = spec.estimator.theta_hat0
    first = held_run(spec, t, u, y, eps=eps, hold=hold, nan_policy=nan_policy)
    N = first.t.shape[0]
    if first.failed_at is not None:
        # the information of the samples the first pass gave; none: its error
        N = first.failed_at
        if N < 2:
            first.raise_for_status()
        warnings.warn(f"Gamma = 'auto': the first pass (θ̂ held at θ̂₀) stopped at t[{N}] = "
                      f"{first.t[N]:.6g} ({first.message.rstrip('.')}); Γ is taken from the "
                      f"{N} samples before. The observer is likely to stop there too: a "
                      "larger ε or a shorter sample interval helps.", ThetahatWarning,
                      stacklevel=3)
    U = (np.zeros((N, 0)) if u is None
         else np.asarray(u, dtype=np.float64).reshape(first.t.shape[0], -1)[:N])
    Y = np.asarray(y, dtype=np.float64).reshape(first.t.shape[0], -1)[:N]  # NaN rows: skip
    return information_gain(s.require_perturbation("Gamma = 'auto'"),
                            np.concatenate([U, Y], axis=1), first.x_hat[:N],
                            np.asarray(th0, dtype=np.float64),
                            float(first.t[N - 1] - first.t[0]),
                            kappa=auto_kappa(spec.estimator.update_law))


def held_run(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
             eps: float | None = None, hold: Hold = "zoh", nan_policy: str = "raise") -> Any:
    """The file's observer run with θ̂ held at θ̂₀: the first pass of the ``"auto"`` gains.

    The observer's (x̂, φ̂) do not need θ̂ to be right (φ̂ is an extended state), which is
    why :func:`auto_eps` and :func:`auto_gamma` choose on this run.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    t, u, y : array_like
        The record, as for :func:`run_estimator`.
    eps : float, optional
        ε of K(ε) (default the file's; required when the file says ``eps = "auto"``).
    hold : {"zoh", "foh"}
    nan_policy : {"raise", "skip"}

    Returns
    -------
    EstimateResult
        It does not raise when the observer stops: ``failed_at`` says where.

    Raises
    ------
    ModelFileError
        The model has no perturbation or parameter set, or ``eps = "auto"`` and no ``eps``.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, held_run, loads_model
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 2.0, 0.01)
    >>> run = held_run(spec, t, np.sin(t)[:, None], np.sin(t)[:, None])
    >>> bool(np.all(run.theta_hat == spec.estimator.theta_hat0)), run.failed_at
    (True, None)
    """
    from ..estimation.drive import runner
    from ..estimation.observer.laws.base import ConstantLaw
    s = spec.system
    if s.perturbation is None or s.parameter_set is None:
        raise ModelFileError(f"model file {spec.source}: the 'auto' gains need the system's "
                             "perturbation and parameter set; the model has none.")
    if eps is None:
        _refuse_auto_eps(spec)
    th0 = spec.estimator.theta_hat0
    est = estimator_spec(spec, hold=hold, nan_policy=nan_policy)
    held = dataclasses.replace(est, law=ConstantLaw(th0, s.parameter_set))
    obs = _build(held, spec, eps)
    return runner(obs, t).run(t, u, y, throw=False,
                              state0=obs.init(x_hat0=start_x_hat(spec, y), theta_hat0=th0))


def auto_eps(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
             hold: Hold = "zoh", nan_policy: str = "raise") -> EpsChoice:
    """``eps = "auto"`` on a record: the ε whose observer best predicts the next sample.

    Runs the file's observer with θ̂ held at θ̂₀ for ε on a log grid over
    :func:`~thetahat.estimation.observer.auto_eps.eps_bounds` (the chain poles between the
    record's Nyquist rate and fifty time constants in its duration) and scores each run by
    :func:`~thetahat.estimation.observer.auto_eps.prediction_cost`; the least wins
    (:func:`~thetahat.estimation.observer.auto_eps.choose_eps`).

    Parameters
    ----------
    spec : ModelSpec
        From :func:`~thetahat.modelfile.schema.load_model`.
    t, u, y : array_like
        The record, as for :func:`run_estimator`.
    hold : {"zoh", "foh"}
        u between the samples, for the observer and the prediction.
    nan_policy : {"raise", "skip"}
        As for :func:`run_estimator`; missing samples are left out of the criterion.

    Returns
    -------
    EpsChoice
        ``.eps`` and the scan behind it.

    Raises
    ------
    ModelFileError
        The model has no perturbation or parameter set.
    DesignError
        The observer stopped at every ε of the range (the message says why the first run
        did: NaN samples under ``nan_policy="raise"``, a divergence), or the record has too
        few samples to score (fewer than r + 3).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, auto_eps, loads_model
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 20.0, 0.01)
    >>> choice = auto_eps(spec, t, np.sin(t)[:, None], np.sin(t)[:, None])
    >>> bool(choice.bounds[0] <= choice.eps <= choice.bounds[1])
    True
    """
    from ..estimation.observer.auto_eps import (TRANSIENT_FRACTION, choose_eps, eps_bounds,
                                                prediction_cost)
    s = spec.system
    t = as_samples("t", seconds_from_first("t", t))
    u = None if u is None else as_samples("u", u)
    y = as_samples("y", y)
    design, _ = design_gains(spec, 1.0)
    poles = np.abs(np.concatenate([np.asarray(c, dtype=complex).ravel()
                                   for c in design.chain_poles]))
    N = t.shape[0]
    skip = int(TRANSIENT_FRACTION * N)
    if N - 1 - skip < s.r + 2:
        raise DesignError(f"eps = 'auto' scores the observer's predictions of the record's "
                          f"samples and needs at least {s.r + 3} of them; the record has {N}. "
                          "Give eps in [estimator] (or eps=).")
    bounds = eps_bounds(poles, float(np.median(np.diff(t))), float(t[-1] - t[0]))
    why: list[str] = []                 # why the runs that failed failed, the first kept

    def cost(eps: float) -> float:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                run = held_run(spec, t, u, y, eps=eps, hold=hold, nan_policy=nan_policy)
            except (DesignError, NonFiniteError, ArithmeticError) as exc:
                why.append(f"at ε = {eps:.3g}: {exc}")
                return np.inf
        if run.failed_at is not None:
            why.append(f"at ε = {eps:.3g}: {run.message}")
            return np.inf
        return prediction_cost(s.A, s.B, s.E, s.C, t, u, y, run.x_hat, run.phi_hat,
                               hold=hold, skip=skip)

    try:
        return choose_eps(cost, bounds)
    except DesignError as exc:          # every run failed: say why the first one did
        if not why:
            raise
        raise DesignError(f"{str(exc).rstrip('.')}; {why[0]}") from exc


def _check_theta_star(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike) -> None:
    """The law's θ* on this record, before the observer runs (a clear error, not a late one)."""
    s = spec.system
    theta_star = getattr(spec.estimator.update_law, "theta_star", None)
    if theta_star is not None:
        if s.perturbation is None or s.parameter_set is None:
            raise ModelFileError(f"model file {spec.source}: θ* needs the system's perturbation "
                                 "and parameter set; the model has none.")
        check_theta_star(theta_star, s.perturbation, s.parameter_set, s.C, t, u, y)


def _trust(spec: ModelSpec, result: EstimateResult, u: ArrayLike | None, y: ArrayLike,
           compiled: bool | None, x0: FloatArray, noise_std: ArrayLike | None,
           hold: str, fits: str) -> TrustReport:
    """The trust report of a run of the file's estimator on its record: the guard's band of a
    guarded run, the σ given by the user (else the one the estimator used), θ̂'s path, for
    the paper's observer (NumPy, compiled or C: one result type) the law's conditions along
    the run, and how θ̂ was made (``fits``, :attr:`TrustReport.fits`: what the warnings
    advise)."""
    from ..estimation.protocol import ObserverDiagnostics
    from ..estimation.statistical.guarded import GuardedDiagnostics
    from ..estimation.statistical.trust import trust_report
    d = result.diagnostics
    band = d.band if isinstance(d, GuardedDiagnostics) else None
    sigma = getattr(d, "noise_std", None)
    if noise_std is not None:
        sigma = np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (spec.system.r,))
    N = result.t.shape[0]
    U = np.zeros((N, 0)) if u is None else np.asarray(u, dtype=np.float64).reshape(N, -1)
    Y = np.asarray(y, dtype=np.float64).reshape(N, -1)
    conditions = None
    s = spec.system
    if isinstance(d, ObserverDiagnostics) and s.perturbation is not None \
            and s.parameter_set is not None:
        from ..estimation.observer.checks import law_conditions_on_record
        names = spec.signal_names
        conditions = law_conditions_on_record(
            s.perturbation, result.t, np.concatenate([U, Y], axis=1), result.x_hat,
            result.theta_hat, s.parameter_set, law=spec.estimator.update_law,
            names=spec.parameter_names,
            signal_names=names.inputs + names.outputs + names.states)
    return trust_report(s, result.t, np.ascontiguousarray(U), np.ascontiguousarray(Y),
                        result.theta_hat[-1], spec.parameter_names, x_hat0=x0, band=band,
                        noise_std=sigma, compiled=compiled, theta_path=result.theta_hat,
                        law_conditions=conditions, hold=hold, fits=fits,
                        fit_q=_record_fit_q(getattr(d, "fits", ()), result.theta_hat[-1], N))


#: The estimator's last fit is "at θ̂" when θ̂ is within this many of its standard errors of
#: the fit's θ in every component (the guarded estimator's stage 2 takes the record's fit one
#: sample before the end, and moves about 0.02 of them after it).
SAME_THETA_SE = 0.1


def _record_fit_q(fits: Sequence[FitResult], theta: FloatArray, N: int) -> float | None:
    """The process noise q of the estimator's own MAP fit of the record at θ̂ (0: an
    output-error fit), when its last fit covers the record (all samples, or all but the last
    one that stage 2 took after it), is at θ̂ (:data:`SAME_THETA_SE`) and passed its
    consistency test; None otherwise (the trust report then searches q from scratch)."""
    if not fits:
        return None
    last = fits[-1]
    gap = np.abs(np.asarray(theta, dtype=np.float64) - last.theta)
    close = gap <= SAME_THETA_SE * last.theta_se
    if last.k0 != 0 or last.k1 < N - 1 or not last.consistent or not np.all(close):
        return None
    return float(last.process_noise)
