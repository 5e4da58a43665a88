"""Estimation: the paper's observer, the step's back ends and the statistical estimators.

Three concerns, one subpackage each; each subpackage's docstring says what it may import:

* :mod:`thetahat.estimation.paper` — the modified high-gain observer (3), the second observer of
  Sec. VI, the update laws (8) of Propositions 1–4, the projection onto Θ and θ*;
* :mod:`thetahat.estimation.kernels` — one step of the observer and the laws written once
  (``formulas``, ``law_formulas``) and the back ends that run it: NumPy, the numba scalar
  kernel and its cache, batches, the stage-2 model kernels;
* :mod:`thetahat.estimation.statistical` — the joint EKF, the MAP fit, the likelihood with
  process noise, the guarded two-stage estimator, the Cramér–Rao bound and the trust report.

Beside them, :mod:`.protocol` (the one estimator interface and :class:`EstimateResult`) and
:mod:`.results` (the observer's results) are shared by all three.

The public names are the package's (``thetahat.JointEKF``, ``thetahat.crlb``, …). The flat module
paths of 0.2 (``thetahat.estimation.mle`` and the like) still import, with a
:class:`DeprecationWarning` naming the new path; they go in 0.4.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType

#: Where each module of 0.2's flat ``thetahat.estimation`` now lives.
MOVED: dict[str, str] = {
    **{m: "paper" for m in (
        "observer", "records", "redesign", "update_laws", "law_base", "gradient", "inversion",
        "projection", "theta_star", "checks", "auto_gain")},
    **{m: "kernels" for m in (
        "kernel_args", "formulas", "law_formulas", "primitives", "scalar_primitives",
        "scalar_backend", "kernel_cache", "model_kernel", "discretize", "plan", "step",
        "batch_run", "compiled")},
    **{m: "statistical" for m in (
        "ekf", "mle", "guarded", "guard", "likelihood", "crlb", "noise_level", "fit_worker",
        "trust")},
}


class _FlatPaths(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """``import thetahat.estimation.<module>`` of 0.2 resolves to the module's new home."""

    def find_spec(self, fullname: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> ModuleSpec | None:
        head, _, name = fullname.rpartition(".")
        if head != __name__ or name not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return None

    def exec_module(self, module: ModuleType) -> None:
        name = module.__name__.rpartition(".")[2]
        new = f"{__name__}.{MOVED[name]}.{name}"
        warnings.warn(f"{module.__name__} moved to {new}; import it from there "
                      "(the old path goes in thetahat 0.4)", DeprecationWarning, stacklevel=2)
        # The import system returns what sys.modules holds once the loader is done: the
        # module itself, so both paths name one object.
        sys.modules[module.__name__] = importlib.import_module(new)


if not any(isinstance(f, _FlatPaths) for f in sys.meta_path):
    sys.meta_path.append(_FlatPaths())
