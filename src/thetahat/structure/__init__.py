"""The structure of the linear part (Sec. III-A): invariant zeros, left invertibility, the SCB.

:mod:`.zeros` computes the invariant zeros and checks left invertibility and minimum phase,
:mod:`.subspaces` the numerical subspaces they rest on, :mod:`.scb` the special coordinate
basis (6) of (C, A, E) numerically and :mod:`.scb_symbolic` symbolically, and
:mod:`.assumptions` checks Assumption 1 in one call.

What it may import: :mod:`thetahat.model` and the package's helpers. Never the design, the
estimators or anything above them.
"""
