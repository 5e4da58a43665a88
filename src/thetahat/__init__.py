"""thetahat: state, perturbation and parameter estimation for linear systems with nonlinearly
parameterized perturbations — the modular observer of Grip, Saberi & Johansen.

The curated public API; everything else lives in the submodules. The names are imported on
first use (PEP 562, :data:`_EXPORTS`): ``import thetahat`` loads no subpackage, and
``from thetahat import X`` or ``thetahat.X`` imports only the module that defines X.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                    # the real imports, for type checkers and IDEs
    from .codegen import CCode, generate_c
    from .design.design_system import DesignSystemReport, apply_design
    from .design.gains import GainDesign, extended_system, high_gain, modified_high_gain
    from .errors import (CCompilerError, ConvergenceWarning, DesignError, DimensionError,
                         IllConditionedError, IllConditionedWarning, InputLimitError,
                         MissingExtraError, ModelFileError, NonFiniteError,
                         NotLeftInvertibleError, NotMinimumPhaseError, ParameterSetError,
                         ResourceLimitError, SimulationError, SymbolicTimeoutError, ThetahatError,
                         ThetahatWarning, UnstableDesignError, UpdateLawError)
    from .estimation.observer.batch_run import BatchObserverResult, run_batch
    from .estimation.observer.checks import (ExcitationReport, MonotonicityReport, check_monotonicity,
                                    excitation_report)
    from .estimation.observer.compiled import CompiledObserver, compile_observer
    from .estimation.statistical.crlb import CRLBResult, crlb
    from .estimation.statistical.ekf import EKFDiagnostics, JointEKF
    from .estimation.statistical.guarded import GuardedDiagnostics, GuardedEstimator
    from .estimation.statistical.mle import MapDiagnostics, MapEstimator
    from .estimation.protocol import EstimateResult, Estimator, ObserverDiagnostics
    from .estimation.observer.observer import ModifiedHighGainObserver, ObserverEstimate
    from .estimation.observer.plan import StepPlan
    from .estimation.observer.laws.projection import Projection, Saturation, saturate
    from .estimation.observer.redesign import SecondObserver
    from .estimation.observer.laws.theta_star import ThetaStar
    from .estimation.observer.laws import (AlgebraicInversion, ConstantLaw,
                                               FilteredLeastSquares, GradientInversion,
                                               IntermittentInversion, UpdateLaw, smooth_ramp)
    from .fleet import FleetResult, estimate_many
    from .model.interop import from_state_space, to_state_space
    from .model.jacobian_check import JacobianCheck, check_jacobians
    from .model.paramset import Ball, Box, ConvexSet, Ellipsoid, ParameterSet
    from .model.parse import parse_perturbation
    from .model.perturbation import CallablePerturbation, Perturbation, SymbolicPerturbation
    from .model.system import PerturbedLinearSystem
    from .simulation.noise import ColoredNoise, WhiteNoise
    from .simulation.signals import FromArray, Multisine, Steps
    from .simulation.simulate import PlantTrajectory, convergence_check, simulate_plant
    from .spec import EstimatorSpec, SecondObserverSpec
    from .structure.assumptions import AssumptionReport, check_assumption_1
    from .structure.scb import SCBResult, scb
    from .structure.scb_symbolic import SymbolicSCBResult, scb_symbolic
    from .structure.zeros import (invariant_zeros, is_left_invertible, is_minimum_phase,
                                  normal_rank, unstable_zeros)
    from .studies.batch import BatchResult, monte_carlo
    from .studies.metrics import rmse, time_to_within
    from .studies.sweep import SweepResult, eps_sweep
    from .studies.tune import TuneResult, tune_eps_gamma

from ._version import __version__

__all__ = [
    "Estimator", "EstimateResult", "ObserverDiagnostics", "GuardedDiagnostics", "MapDiagnostics",
    "EKFDiagnostics",
    "CRLBResult", "crlb", "JointEKF", "GuardedEstimator", "MapEstimator",
    "BatchObserverResult", "FleetResult", "estimate_many", "TuneResult", "tune_eps_gamma", "CompiledObserver", "compile_observer", "run_batch",
    "EstimatorSpec", "SecondObserverSpec",
    "AlgebraicInversion", "Ball", "Box", "ConstantLaw", "ConvexSet", "Ellipsoid",
    "ExcitationReport", "FilteredLeastSquares", "GradientInversion", "IntermittentInversion",
    "ModifiedHighGainObserver",
    "MonotonicityReport", "ObserverEstimate", "ParameterSet", "Projection",
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

#: Module (relative to this package) that defines each public name.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "codegen": ("CCode", "generate_c"),
    "design.design_system": ("DesignSystemReport", "apply_design"),
    "design.gains": ("GainDesign", "extended_system", "high_gain", "modified_high_gain"),
    "errors": ("CCompilerError", "ConvergenceWarning", "DesignError", "DimensionError",
               "IllConditionedError", "IllConditionedWarning", "InputLimitError",
               "MissingExtraError", "ModelFileError", "NonFiniteError", "NotLeftInvertibleError",
               "NotMinimumPhaseError", "ParameterSetError", "ResourceLimitError",
               "SimulationError", "SymbolicTimeoutError", "ThetahatError", "ThetahatWarning",
               "UnstableDesignError", "UpdateLawError"),
    "estimation.observer.batch_run": ("BatchObserverResult", "run_batch"),
    "estimation.observer.checks": ("ExcitationReport", "MonotonicityReport", "check_monotonicity",
                          "excitation_report"),
    "estimation.observer.compiled": ("CompiledObserver", "compile_observer"),
    "estimation.statistical.crlb": ("CRLBResult", "crlb"),
    "estimation.statistical.ekf": ("EKFDiagnostics", "JointEKF"),
    "estimation.statistical.guarded": ("GuardedDiagnostics", "GuardedEstimator"),
    "estimation.statistical.mle": ("MapDiagnostics", "MapEstimator"),
    "estimation.protocol": ("EstimateResult", "Estimator", "ObserverDiagnostics"),
    "estimation.observer.observer": ("ModifiedHighGainObserver", "ObserverEstimate"),
    "estimation.observer.plan": ("StepPlan",),
    "estimation.observer.laws.projection": ("Projection", "Saturation", "saturate"),
    "estimation.observer.redesign": ("SecondObserver",),
    "estimation.observer.laws.theta_star": ("ThetaStar",),
    "estimation.observer.laws": ("AlgebraicInversion", "ConstantLaw", "FilteredLeastSquares",
                                     "GradientInversion", "IntermittentInversion", "UpdateLaw",
                                     "smooth_ramp"),
    "fleet": ("FleetResult", "estimate_many"),
    "model.interop": ("from_state_space", "to_state_space"),
    "model.jacobian_check": ("JacobianCheck", "check_jacobians"),
    "model.paramset": ("Ball", "Box", "ConvexSet", "Ellipsoid", "ParameterSet"),
    "model.parse": ("parse_perturbation",),
    "model.perturbation": ("CallablePerturbation", "Perturbation", "SymbolicPerturbation"),
    "model.system": ("PerturbedLinearSystem",),
    "simulation.noise": ("ColoredNoise", "WhiteNoise"),
    "simulation.signals": ("FromArray", "Multisine", "Steps"),
    "simulation.simulate": ("PlantTrajectory", "convergence_check", "simulate_plant"),
    "spec": ("EstimatorSpec", "SecondObserverSpec"),
    "structure.assumptions": ("AssumptionReport", "check_assumption_1"),
    "structure.scb": ("SCBResult", "scb"),
    "structure.scb_symbolic": ("SymbolicSCBResult", "scb_symbolic"),
    "structure.zeros": ("invariant_zeros", "is_left_invertible", "is_minimum_phase", "normal_rank",
                        "unstable_zeros"),
    "studies.batch": ("BatchResult", "monte_carlo"),
    "studies.metrics": ("rmse", "time_to_within"),
    "studies.sweep": ("SweepResult", "eps_sweep"),
    "studies.tune": ("TuneResult", "tune_eps_gamma"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}


def __getattr__(name: str) -> Any:
    """Import the module that defines the public ``name`` on first use, and keep the value."""
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'thetahat' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
