"""The step written once, and the back ends that run it.

The step's formulas (:mod:`.formulas`, :mod:`.law_formulas`) over a small vocabulary of
primitives, with the named argument tuples (:mod:`.kernel_args`); the NumPy binding
(:mod:`.primitives`, :mod:`.step`, :mod:`.batch_run`), the scalar binding emitted as a numba
module (:mod:`.scalar_primitives`, :mod:`.scalar_backend`, :mod:`.compiled`) with its on-disk
cache (:mod:`.kernel_cache`), the stage-2 plant kernels (:mod:`.model_kernel`), and the
observer's discretisation and plan (:mod:`.discretize`, :mod:`.plan`), and the one status
enum every binding returns (:mod:`.status`). The C printer in
:mod:`thetahat.codegen` reads the same formulas.

What it may import: :mod:`thetahat.model`, the package's helpers, and from
:mod:`thetahat.estimation.paper` only the objects a binding binds (laws, θ*, the observer
that a compiled kernel stands in for). Never the statistical estimators.
"""
