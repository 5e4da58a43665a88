"""Simulated data for tests, studies and examples: the plant integrated, inputs and noise.

:mod:`.simulate` integrates the perturbed plant (1) with SciPy and checks convergence,
:mod:`.signals` builds input signals (steps, multisines, arrays) and :mod:`.noise` the
measurement noise (white or coloured).

What it may import: :mod:`thetahat.model` and the package's helpers. Never the estimators.
"""
