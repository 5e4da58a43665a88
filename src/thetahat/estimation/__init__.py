"""Estimation: one protocol, one status, one driver, and two rooms of estimators.

* :mod:`.protocol` — the one estimator interface (:class:`~.protocol.Estimator`) and the one
  result (:class:`~.protocol.EstimateResult`, which carries a :class:`~.status.Status`);
* :mod:`.status` — how a step or a run ended, in every back end (NumPy, numba, C, the EKF and
  the MAP fits), and the one failure behaviour;
* :mod:`.drive` — the back ends each estimator can run on and the choice among them;
* :mod:`.kernels` — the mechanism under the back ends (primitives, printed numba modules);
* :mod:`.observer` — the paper's observer (3), its update laws (8) and Sec. VI;
* :mod:`.statistical` — the joint EKF, the MAP fits, the guarded two-stage estimator, the
  Cramér–Rao bound and the trust report.

The arrows point down: statistical → observer → kernels → (protocol, status, drive); none of
them imports :mod:`thetahat.codegen`, the model files or the command line (checked by the
import contracts in ``pyproject.toml``). The public names are the package's
(``thetahat.JointEKF``, ``thetahat.crlb``, …).
"""
