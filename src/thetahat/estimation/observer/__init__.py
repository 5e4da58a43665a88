"""The paper's observer: equation (3), the update laws (8), Sec. VI, and the back ends that run them.

One room for everything the paper's method is made of:

* the observer (3) (:mod:`.observer`), its checked records (:mod:`.records`), the second
  observer of Sec. VI (:mod:`.redesign`), the sampled checks of the Propositions' conditions
  (:mod:`.checks`), the automatic Γ (:mod:`.auto_gain`) and the start x̂(0)
  (:mod:`.initial_state`);
* the update laws of Sec. IV with the projection onto Θ and θ* (:mod:`.laws`);
* one sample of (3), (8) and Sec. VI written once (:mod:`.formulas`, :mod:`.laws.formulas`),
  its discretisation and plan (:mod:`.discretize`, :mod:`.plan`), and the back ends that run
  it: NumPy for one row (:mod:`.step`, the record loop, its status and result in
  :mod:`.record_run`) and for a batch (:mod:`.batch_run`), the numba kernel printed from the
  same formulas (:mod:`.kernel_source`, :mod:`.compiled`, the data it reads in
  :mod:`.kernel_data`).

What it may import: :mod:`thetahat.model`, :mod:`thetahat.structure`, the package's helpers
(errors, limits, validation, safe_io), :mod:`thetahat.estimation.protocol`,
:mod:`thetahat.estimation.status`, :mod:`thetahat.estimation.drive` and the mechanism of
:mod:`thetahat.estimation.kernels`. Never :mod:`thetahat.estimation.statistical`, never
:mod:`thetahat.codegen` (the C back end registers itself with :mod:`thetahat.estimation.drive`).
"""
