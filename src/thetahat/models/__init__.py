"""Shipped models: the paper's LuGre DC motor, the EMPS drive, the Silverbox circuit, a
two-inertia drive, and the small systems that exercise Propositions 1–4.

:mod:`.lugre` (the paper's example, Sec. VIII: plant, designs, observers, every method) with
its report :mod:`.lugre_report`; :mod:`.emps` (the measured EMPS benchmark) with
:mod:`.emps_report`; :mod:`.silverbox` (the measured Silverbox benchmark, an electronic Duffing
oscillator) with :mod:`.silverbox_report`; :mod:`.two_inertia` (MIMO); :mod:`.prop1_sinh`, :mod:`.prop2_tanh`,
:mod:`.prop3_monotone`, :mod:`.prop4_pe` (one per Proposition). Tests, examples, the docs and
the benchmarks all import them from here.

What it may import: anything below the command line (the estimators, the model files, the
studies, the readers). Nothing imports it but the command line and the tests.
"""
