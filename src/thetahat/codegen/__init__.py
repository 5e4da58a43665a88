"""C code generation: the designed observer as dependency-free C99 for a controller.

:func:`generate_c` turns a built :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`
into ``<name>.h``/``<name>.c`` (the step at a fixed dt, no heap, caller-owned state), a CSV
harness ``<name>_main.c`` and a ``Makefile``; :func:`thetahat.modelfile.generate_c_from_model`
(``thetahat codegen MODEL --dt … -o DIR``) does the same from a model file.
:func:`~thetahat.codegen.ekf_c.generate_ekf_c` prints the joint EKF on col(x, θ) (stage 2's
kernels) the same way (``thetahat codegen MODEL --method ekf``), and
:func:`~thetahat.codegen.guarded_c.generate_guarded_c` the guarded estimator: both, with the
guard between them and no fits (``--method guarded``).
:mod:`thetahat.codegen.loader` compiles the result with the system C compiler and loads it with
ctypes, and :mod:`thetahat.codegen.native` registers that C as the fastest back end of the
observer's run (:mod:`thetahat.estimation.drive`).

What it may import: :mod:`thetahat.estimation` (the observer and the formulas it prints), the
model and the package's helpers. Never the model files, the studies or the command line.
"""

from .ekf_c import EKFCode, generate_ekf_c
from .generate import CCode, generate_c, model_hash
from .guarded_c import GuardedCode, generate_guarded_c

__all__ = ["CCode", "EKFCode", "GuardedCode", "generate_c", "generate_ekf_c",
           "generate_guarded_c", "model_hash"]
