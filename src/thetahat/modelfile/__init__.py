"""Model files: a :class:`~thetahat.model.system.PerturbedLinearSystem` and its estimator as text.

Split by job: :mod:`.schema` reads and validates a file into a :class:`ModelSpec` (the file
format is documented there), against the tables of keys of :mod:`.keys` (one per section),
with :mod:`.text` (TOML or JSON within limits) and :mod:`.section` (one section's values and
messages); :mod:`.assembly` builds and runs the estimator it describes (as an
:class:`~thetahat.spec.EstimatorSpec`), :mod:`.report` analyses it (``thetahat analyze``) and
:mod:`.study` simulates its ``[scenario]`` for ``thetahat sweep`` and ``thetahat tune``, and
:mod:`.codegen` prints its observer as C (``thetahat codegen``).

What it may import: the studies (:mod:`thetahat.studies`: the checks of a record, the
summary), :mod:`thetahat.methods`, :mod:`thetahat.spec` and everything below them. Fleets,
the shipped models and the command line import it.
"""

from .assembly import (ObserverGains, auto_eps, auto_gamma, build_estimator, build_observer,
                       design_gains, design_matrices, estimator_spec, held_run, resolve_gains,
                       run_estimator, start_x_hat)
from .holds import split_hold
from .codegen import (generate_c_from_model, generate_ekf_c_from_model,
                      generate_guarded_c_from_model)
from .report import ModelAnalysis, analyze_model
from ..methods import ESTIMATION_METHODS
from .keys import LAWS
from .schema import (EXAMPLE_MODEL, EstimatorOptions, ModelSpec, ScenarioOptions,
                     SecondObserverOptions, load_model, loads_model)
from .study import simulate_model, study_simulator

__all__ = ["auto_eps", "auto_gamma", "held_run", "ESTIMATION_METHODS", "EXAMPLE_MODEL", "LAWS",
           "EstimatorOptions",
           "ModelAnalysis", "ObserverGains", "resolve_gains",
           "ModelSpec", "ScenarioOptions", "SecondObserverOptions", "analyze_model",
           "build_estimator", "build_observer", "design_gains", "design_matrices",
           "estimator_spec", "generate_c_from_model", "generate_ekf_c_from_model",
           "generate_guarded_c_from_model",
           "load_model", "loads_model", "run_estimator", "simulate_model", "split_hold",
           "start_x_hat", "study_simulator"]
