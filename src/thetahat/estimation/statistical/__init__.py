"""The statistical estimators: efficient where the paper's observer is guaranteed.

What lives here, module by module:

* :mod:`.common` — what the estimators share: start values, the priors of θ and x(0), σ, the
  sampling interval, and how a run that stopped is reported;
* :mod:`.ekf_kernels` — the joint EKF's per-sample kernels on col(x, θ) (predict, gain,
  Joseph-form update, the loop), compiled with the model;
* :mod:`.ekf` — the joint extended Kalman filter (:class:`~.ekf.JointEKF`, method "ekf");
* :mod:`.map_fit` — the MAP fits of (x(t₀), θ) by Gauss–Newton, their schedule and their use
  as the EKF's prior; :mod:`.likelihood` — the fit of a model with process noise on φ;
  :mod:`.window` — bounded fits: a moving window with the EKF's posterior as arrival cost;
* :mod:`.mle` — the MAP estimator (:class:`~.mle.MapEstimator`, method "mle");
* :mod:`.guard` and :mod:`.guarded` — the guard between the stages and the two-stage guarded
  estimator (:class:`~.guarded.GuardedEstimator`, method "guarded"); :mod:`.fit_worker` — its
  fits off the sample path;
* :mod:`.crlb` — the Cramér–Rao bound; :mod:`.trust` — the trust report; :mod:`.noise_level`
  — σ from the data; :mod:`.input_hold` — stage 2's input samples; :mod:`.stage2_set` — Θ as
  stage 2 sees it (bounds, the covariance-weighted projection onto any convex set);
  :mod:`.plant_kernel` — the plant's sampled-data map as compiled kernels.

Every estimator's ``run`` takes ``throw``: a divergence or a singular solve stops the run
with a :class:`~thetahat.estimation.status.Status` that is raised (``throw=True``) or returned
with NaN rows from ``failed_at`` on (``throw=False``).

What it may import: everything below it — :mod:`thetahat.model`, the package's helpers, the
bottom of the estimation wing (:mod:`~thetahat.estimation.protocol`,
:mod:`~thetahat.estimation.records`, :mod:`~thetahat.estimation.status`),
:mod:`thetahat.estimation.kernels` (model kernels) and :mod:`thetahat.estimation.observer`
(stage 1 is the paper's observer). Inside the room the arrows point from the estimators
(``guarded``, ``mle``, ``ekf``, ``trust``, ``crlb``) down to ``window``, ``map_fit`` and
``likelihood``, then
``ekf_kernels``, ``common``, ``plant_kernel``, ``stage2_set``, ``noise_level`` and
``input_hold``; no module imports an estimator's module for a helper.
"""
