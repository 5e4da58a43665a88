"""Studies of an estimator on simulated data: Monte-Carlo batches, ε sweeps, (ε, Γ) tuning.

:mod:`.batch` runs one function per seed (sequentially or in worker processes),
:mod:`.metrics` measures an estimate against the truth, :mod:`.runs` measures one study run,
:mod:`.sweep` runs the ε sweep of Sec. VII and :mod:`.tune` the (ε, Γ) search. A study takes
an :class:`~thetahat.spec.EstimatorSpec` (one SCB for every ε and Γ) or a callable that
builds observers.
"""
