"""The mechanism under every back end: one printer from the formulas to NumPy, numba and C.

The step's formulas are written once, in a small subset of Python over named blocks
(:mod:`.subset`: views such as ``x_hat = s[0:NX]``, block statements such as
``F_x[:] = P.A @ x_hat + P.B @ u + P.E @ g``, element statements, the vocabulary of
:mod:`.primitives`). One printer (:class:`.printer.Program`) resolves the views and blocks at
print time for three targets, and every piece of generated Python is a module file printed
from syntax trees and imported from the cache (:mod:`.modules`, :mod:`.kernel_cache`):

* NumPy: the formulas printed for one row (``"row"``) or for rows along a leading axis
  (``"batch"``) into a module whose ``bind(**names)`` closes them over the model functions and
  the law's hooks (:func:`.modules.numpy_binding`);
* numba: the formulas printed as scalar loops (``"scalar"``), with the scalar functions of
  :mod:`.scalar_primitives` and the model printed from SymPy, into one module compiled with
  ``numba.njit(cache=True)`` (:mod:`thetahat.estimation.observer.kernel_source`);
* C: the same scalar print, specialised per call and written as C99 by
  :mod:`thetahat.codegen.c_printer`.

Stage 2's kernels use the same writer: the plant model (``rhs_jac`` from SymPy with the RK4
kernels) is one printed module, and every other stage-2 kernel is a module-level function
printed with its free names bound (:meth:`.modules.ModuleText.bound`). The named argument
tuples of the formulas and their shapes are in :mod:`.kernel_args`, the projection onto a convex Θ as kernels in :mod:`.set_projection`.

What it may import: :mod:`thetahat.model`, the package's helpers and
:mod:`thetahat.estimation.status`. Nothing above it.
"""
