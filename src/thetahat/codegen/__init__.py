"""C code generation: the designed observer as dependency-free C99 for a controller.

:func:`generate_c` turns a built :class:`~thetahat.estimation.paper.observer.ModifiedHighGainObserver`
into ``<name>.h``/``<name>.c`` (the step at a fixed dt, no heap, caller-owned state), a CSV
harness ``<name>_main.c`` and a ``Makefile``; ``thetahat codegen MODEL --dt … -o DIR`` does the
same from a model file. :mod:`thetahat.codegen.loader` compiles the result with the system C
compiler and loads it with ctypes (for tests and benchmarks).
"""

from .generate import CCode, generate_c, generate_c_from_model, model_hash

__all__ = ["CCode", "generate_c", "generate_c_from_model", "model_hash"]
