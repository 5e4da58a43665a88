"""thetahat: state, perturbation and parameter estimation for linear systems with nonlinearly
parameterized perturbations — the modular observer of Grip, Saberi & Johansen.

The curated public API; everything else lives in the submodules.
"""

from .codegen import CCode, generate_c
from .design.design_system import DesignSystemReport, apply_design
from .design.gains import GainDesign, extended_system, high_gain, modified_high_gain
from .estimation.batch_run import BatchObserverResult, run_batch
from .estimation.checks import (ExcitationReport, MonotonicityReport, check_monotonicity,
                                excitation_report)
from .estimation.compiled import CompiledObserver, compile_observer
from .estimation.crlb import CRLBResult, crlb
from .estimation.ekf import JointEKF
from .estimation.guarded import GuardedEstimator, GuardedResult
from .estimation.mle import MapEstimator
from .estimation.observer import ModifiedHighGainObserver, ObserverEstimate, ObserverResult
from .estimation.plan import StepPlan
from .estimation.protocol import EstimateResult, Estimator, ObserverDiagnostics
from .estimation.ekf import EKFDiagnostics
from .estimation.guarded import GuardedDiagnostics
from .estimation.mle import MapDiagnostics
from .estimation.projection import Projection, Saturation, saturate
from .estimation.redesign import SecondObserver
from .estimation.theta_star import ThetaStar
from .estimation.update_laws import (AlgebraicInversion, ConstantLaw, GradientInversion,
                                     IntermittentInversion, UpdateLaw, smooth_ramp)
from .errors import (CCompilerError, ConvergenceWarning, DesignError, DimensionError, IllConditionedWarning,
                     MissingExtraError, ModelFileError, NonFiniteError, SimulationError, NotLeftInvertibleError,
                     NotMinimumPhaseError, ParameterSetError, ThetahatError, ThetahatWarning,
                     UpdateLawError)
from .errors import (IllConditionedError, InputLimitError, ResourceLimitError,
                     SymbolicTimeoutError, UnstableDesignError)
from .model.interop import from_state_space, to_state_space
from .model.paramset import Ball, Box, ConvexSet, Ellipsoid, ParameterSet
from .model.parse import parse_perturbation
from .model.jacobian_check import JacobianCheck, check_jacobians
from .model.perturbation import CallablePerturbation, Perturbation, SymbolicPerturbation
from .model.system import PerturbedLinearSystem
from .fleet import FleetResult, estimate_many
from .simulation.noise import ColoredNoise, WhiteNoise
from .simulation.signals import FromArray, Multisine, Steps
from .simulation.simulate import PlantTrajectory, convergence_check, simulate_plant
from .spec import EstimatorSpec, SecondObserverSpec
from .studies.batch import BatchResult, monte_carlo
from .studies.metrics import rmse, time_to_within
from .studies.sweep import SweepResult, eps_sweep
from .studies.tune import TuneResult, tune_eps_gamma
from .structure.assumptions import AssumptionReport, check_assumption_1
from .structure.scb import SCBResult, scb
from .structure.scb_symbolic import SymbolicSCBResult, scb_symbolic
from .structure.zeros import (invariant_zeros, is_left_invertible, is_minimum_phase,
                              normal_rank, unstable_zeros)

__version__ = "0.1.0"

__all__ = [
    "Estimator", "EstimateResult", "ObserverDiagnostics", "GuardedDiagnostics", "MapDiagnostics",
    "EKFDiagnostics",
    "CRLBResult", "crlb", "JointEKF", "GuardedEstimator", "GuardedResult", "MapEstimator",
    "BatchObserverResult", "FleetResult", "estimate_many", "TuneResult", "tune_eps_gamma", "CompiledObserver", "compile_observer", "run_batch",
    "EstimatorSpec", "SecondObserverSpec",
    "AlgebraicInversion", "Ball", "Box", "ConstantLaw", "ConvexSet", "Ellipsoid",
    "ExcitationReport", "GradientInversion", "IntermittentInversion", "ModifiedHighGainObserver",
    "MonotonicityReport", "ObserverEstimate", "ObserverResult", "ParameterSet", "Projection",
    "Saturation", "SecondObserver", "SweepResult", "UpdateLaw", "check_monotonicity",
    "eps_sweep", "excitation_report", "rmse", "saturate", "smooth_ramp", "time_to_within",
    "AssumptionReport", "BatchResult", "ColoredNoise", "FromArray", "Multisine",
    "PlantTrajectory", "Steps", "WhiteNoise", "convergence_check", "monte_carlo",
    "simulate_plant", "CallablePerturbation", "JacobianCheck", "Perturbation",
    "SymbolicPerturbation", "check_jacobians", "from_state_space", "parse_perturbation",
    "to_state_space", "ConvergenceWarning", "DesignError", "DesignSystemReport",
    "DimensionError", "GainDesign", "MissingExtraError", "IllConditionedWarning", "ModelFileError", "SimulationError",
    "NonFiniteError", "NotLeftInvertibleError", "NotMinimumPhaseError", "ParameterSetError",
    "PerturbedLinearSystem", "SCBResult", "SymbolicSCBResult", "ThetahatError", "ThetahatWarning", "UpdateLawError",
    "apply_design", "check_assumption_1", "extended_system", "high_gain", "invariant_zeros",
    "is_left_invertible", "is_minimum_phase", "modified_high_gain", "normal_rank", "scb", "scb_symbolic",
    "unstable_zeros", "__version__",
    "IllConditionedError", "InputLimitError", "ResourceLimitError", "SymbolicTimeoutError",
    "UnstableDesignError",
    "StepPlan", "ThetaStar",
    "CCode", "generate_c", "CCompilerError",
]
