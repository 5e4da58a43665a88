"""The paper's observer and its parameter estimators.

The modified high-gain observer (3) of Sec. III (:mod:`.observer`), its checked records
(:mod:`.records`), the second observer of Sec. VI (:mod:`.redesign`), the update laws (8) of
Propositions 1–4 (:mod:`.law_base`, :mod:`.inversion`, :mod:`.gradient`), the projection onto Θ
(:mod:`.projection`), the inversion θ* (:mod:`.theta_star`), the sampled checks of the
Propositions' conditions (:mod:`.checks`), the automatic gain Γ (:mod:`.auto_gain`) and the
start x̂(0) nearest the prior that fits the first sample (:mod:`.initial_state`).

What it may import: :mod:`thetahat.model`, :mod:`thetahat.structure`, the package's helpers
(errors, limits, validation), :mod:`thetahat.estimation.protocol` and the step's formulas and
back ends in :mod:`thetahat.estimation.kernels` (the laws bind ``law_formulas`` with the
primitives; the observer chooses a back end). Never the statistical estimators.
"""
