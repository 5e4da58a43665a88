"""Studies of an estimator on simulated data: Monte-Carlo batches, ε sweeps, (ε, Γ) tuning.

:mod:`.batch` runs one function per seed (sequentially or in worker processes),
:mod:`.metrics` measures an estimate against the truth, :mod:`.runs` measures one study run,
:mod:`.sweep` runs the ε sweep of Sec. VII and :mod:`.tune` the (ε, Γ) search. A study takes
an :class:`~thetahat.spec.EstimatorSpec` (one SCB for every ε and Γ) or a callable that
builds observers. :mod:`.information` checks a record (does information reach the update law?
is g defined on the data?) and explains a failed run; :func:`.metrics.estimate_summary` writes
the summary of an estimate.

What it may import: :mod:`thetahat.spec`, :mod:`thetahat.methods` and everything below them.
Model files (:func:`thetahat.modelfile.run_estimator` diagnoses its runs with
:mod:`.information`), the shipped models, fleets and the command line import it.
"""
