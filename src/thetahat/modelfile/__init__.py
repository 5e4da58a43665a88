"""Model files: a :class:`~thetahat.model.system.PerturbedLinearSystem` and its estimator as text.

Split by job: :mod:`.schema` reads and validates a file into a :class:`ModelSpec` (the file
format is documented there), :mod:`.assembly` builds and runs the estimator it describes, and
:mod:`.report` analyses it (``thetahat analyze``).
"""

from .assembly import build_observer, design_gains, design_matrices, run_estimator
from .report import ModelAnalysis, analyze_model
from .schema import (ESTIMATION_METHODS, EXAMPLE_MODEL, LAWS, EstimatorOptions, ModelSpec, SecondObserverOptions,
                     load_model, loads_model)

__all__ = ["ESTIMATION_METHODS", "EXAMPLE_MODEL", "LAWS", "EstimatorOptions", "ModelAnalysis", "ModelSpec",
           "SecondObserverOptions", "analyze_model", "build_observer", "design_gains",
           "design_matrices", "load_model", "loads_model", "run_estimator"]
