"""The mechanism under every back end: the primitives a step is written in, and compiled kernels.

The vocabulary of the step's formulas and its NumPy implementation (:mod:`.primitives`), the
same vocabulary for one scalar row (:mod:`.scalar_primitives`), the named argument tuples of
the formulas (:mod:`.kernel_args`), the projection onto a convex Θ as kernels
(:mod:`.set_projection`) and the on-disk cache of printed numba modules (:mod:`.kernel_cache`).
The observer (:mod:`thetahat.estimation.observer`), stage 2's plant kernels
(:mod:`thetahat.estimation.statistical.plant_kernel`) and the C printer
(:mod:`thetahat.codegen`) build on it.

What it may import: :mod:`thetahat.model`, the package's helpers and
:mod:`thetahat.estimation.status`. Nothing above it.
"""
