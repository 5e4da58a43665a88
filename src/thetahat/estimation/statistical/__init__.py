"""The statistical estimators: efficient where the paper's observer is guaranteed.

The joint extended Kalman filter (:mod:`.ekf`), the MAP / maximum-likelihood fit and its
information schedule (:mod:`.mle`), the likelihood with process noise (:mod:`.likelihood`), the
two-stage guarded estimator and its guard (:mod:`.guarded`, :mod:`.guard`), the off-path fit
worker (:mod:`.fit_worker`), the Cramér–Rao bound (:mod:`.crlb`), the noise level
(:mod:`.noise_level`), Θ as stage 2 sees it — bounds and the covariance-weighted projection
onto any convex set (:mod:`.stage2_set`) — and the trust report (:mod:`.trust`).

What it may import: everything below it — :mod:`thetahat.model`, the package's helpers,
:mod:`thetahat.estimation.protocol`, :mod:`thetahat.estimation.kernels` (model kernels) and
:mod:`thetahat.estimation.observer` (stage 1 is the paper's observer).
"""
