"""Tests of ``run_batch``: B observer runs vectorised over a batch axis (pure numpy).

Every test compares with a loop of ``ModifiedHighGainObserver.run``, the reference.
"""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from thetahat.errors import DimensionError, NonFiniteError
from thetahat.estimation.observer.batch_run import BatchObserverResult, run_batch
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.protocol import EstimateResult
from thetahat.estimation.status import Status
from thetahat.estimation.observer.laws import ConstantLaw, GradientInversion
from thetahat.model.paramset import Box
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.model.system import PerturbedLinearSystem
from thetahat.models import lugre
from diverging import unstable_observer

#: Agreement with a loop of ``run``, relative to each column's largest |value|. The batch step
#: is the same formula; only the summation order of the small matrix products (batched matmul
#: vs. matrix-vector products) and LAPACK's batched solve differ: rounding, measured below
#: 1e-15 on the DC motor.
BATCH_RTOL = 1e-10
NAMES = ("x_hat", "phi_hat", "theta_hat", "x_hat_refined")


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    scale = np.maximum(np.max(np.abs(b), axis=0), np.finfo(float).tiny)
    return float(np.max(np.abs(a - b) / scale))


def assert_matches(res: BatchObserverResult, refs: list[EstimateResult]) -> None:
    assert len(res) == len(refs)
    for i, ref in enumerate(refs):
        for name in NAMES:
            a, b = getattr(res[i], name), getattr(ref, name)
            if b is None:
                assert a is None
            else:
                assert rel_err(a, b) <= BATCH_RTOL, (i, name)
        assert np.array_equal(res[i].skipped, ref.skipped)


@pytest.fixture(scope="module")
def motor_records():
    """Three noise seeds of the DC motor (Sec. VIII), 0.6 s at 1 kHz."""
    runs = [lugre.simulate(seed=s, t_end=0.6) for s in range(3)]
    return runs[0].t, np.stack([r.u for r in runs]), np.stack([r.y for r in runs])


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_one_observer_many_records_matches_loop_of_run(motor_records, hold):
    t, U, Y = motor_records
    obs = lugre.observer().with_run_options(hold=hold)
    res = run_batch(obs, t, U, Y)
    assert_matches(res, [obs.run(t, U[b], Y[b]) for b in range(len(U))])


def test_observers_differing_in_eps_and_gamma(motor_records):
    t, U, Y = motor_records
    obs = [lugre.observer(eps=1.0, Gamma=1.0), lugre.observer(eps=0.5, Gamma=4.0),
           lugre.observer(eps=0.2, Gamma=1.0, eps2=0.5)]
    res = run_batch(obs, t, U, Y)
    assert_matches(res, [o.run(t, U[b], Y[b]) for b, o in enumerate(obs)])
    th = res.theta_hat
    assert (th >= 0.05).all() and (th <= 1.0).all()              # θ̂ ∈ Θ at every sample
    assert not np.allclose(th[0], th[1])                         # the gains did differ


def test_one_state0_for_all_and_state0_per_run(motor_records):
    t, U, Y = motor_records
    obs = lugre.observer()
    s0 = obs.init(x_hat0=[0.1, 0.0], theta_hat0=[0.9])
    res = run_batch(obs, t[:50], U[:, :50], Y[:, :50], state0=s0)
    assert np.allclose(res.theta_hat[:, 0, 0], 0.9)
    S0 = np.stack([obs.init(theta_hat0=[th]) for th in (0.1, 0.5, 0.9)])
    res = run_batch(obs, t[:50], U[:, :50], Y[:, :50], state0=S0)
    assert_matches(res, [obs.run(t[:50], U[b, :50], Y[b, :50], state0=S0[b]) for b in range(3)])


# --------------------------------------------------------------------------- MIMO, gradient law
U_, Y1, Y2, X1, X2, T1, T2 = sp.symbols("u y1 y2 x1 x2 theta1 theta2", real=True)
TOY_G = SymbolicPerturbation.from_sympy(
    [T1 * sp.tanh(X1) + U_ / 10, T2 * X2 / (1 + X2**2) + Y1 * Y2 / 20],
    u=[U_], y=[Y1, Y2], x=[X1, X2], theta=[T1, T2])
TOY_BOX = Box([0.2, 0.1], [2.0, 3.0])
TOY = PerturbedLinearSystem(A=[[0.0, 1.0], [-1.0, -0.5]], B=[[0.0], [1.0]], C=np.eye(2),
                            E=np.eye(2), perturbation=TOY_G, parameter_set=TOY_BOX)


def toy_records(B: int, N: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    t = np.arange(N) * 1e-3
    Y = np.c_[np.sin(2 * t), 1.5 * np.cos(t)] + 0.05 * rng.standard_normal((B, N, 2))
    U = np.broadcast_to(np.sin(3 * t)[:, None], (B, N, 1))
    return t, U, Y


def test_gradient_laws_with_different_gamma_are_grouped():
    laws = [GradientInversion(TOY_G, np.diag(d), TOY_BOX) for d in ([0.5, 2.0], [3.0, 1.0])]
    obs = [ModifiedHighGainObserver(system=TOY, K_x=k * np.eye(2), K_phi=k * np.eye(2),
                                    update_law=law, hold="foh")
           for k, law in zip((4.0, 6.0), laws)]
    t, U, Y = toy_records(2)
    res = run_batch(obs, t, U, Y)
    assert_matches(res, [o.run(t, U[b], Y[b]) for b, o in enumerate(obs)])
    assert TOY_BOX.contains(res.theta_hat).all()


def test_missing_samples_are_skipped_per_run():
    obs = [ModifiedHighGainObserver(system=TOY, K_x=4 * np.eye(2), K_phi=4 * np.eye(2),
                                    update_law=GradientInversion(TOY_G, gamma, TOY_BOX),
                                    nan_policy="skip") for gamma in (1.0, 2.0, 1.0)]
    t, U, Y = toy_records(3)
    Y = Y.copy()
    Y[0, 100:130, 1] = np.nan
    Y[2, 5, :] = np.nan
    for hold in ("zoh", "foh"):
        held = [o.with_run_options(hold=hold) for o in obs]
        res = run_batch(held, t, U, Y)
        assert_matches(res, [o.run(t, U[b], Y[b]) for b, o in enumerate(held)])
    assert res.skipped.sum() == 31 and res.skipped[2, 5]


# --------------------------------------------------------------------------- errors, result
def test_incompatible_observers_are_rejected(motor_records):
    t, U, Y = motor_records
    other_law = ModifiedHighGainObserver.from_design(
        lugre.system(), lugre.designs()[0], ConstantLaw([0.3], Box([0.05], [1.0])))
    with pytest.raises(DimensionError, match="differs from observers\\[0\\] in the update law"):
        run_batch([lugre.observer(), other_law], t, U[:2], Y[:2])
    with pytest.raises(DimensionError, match="second observer"):
        run_batch([lugre.observer(), lugre.observer(second=False)], t, U[:2], Y[:2])
    with pytest.raises(DimensionError, match="in hold"):
        run_batch([lugre.observer(), lugre.observer().with_run_options(hold="foh")], t,
                  U[:2], Y[:2])


def test_input_errors(motor_records):
    t, U, Y = motor_records
    obs = lugre.observer()
    with pytest.raises(DimensionError, match=r"Y must have shape \(2, "):
        run_batch([obs, obs], t, U, Y)
    with pytest.raises(DimensionError, match="strictly increasing"):
        run_batch(obs, t[::-1], U, Y)
    Yn = Y.copy()
    Yn[1, 7, 0] = np.nan
    with pytest.raises(NonFiniteError, match="run 1 at index 7"):
        run_batch(obs, t, U, Yn)
    with pytest.raises(DimensionError, match="state0"):
        run_batch(obs, t, U, Y, state0=np.zeros(3))


def test_result_indexing_and_repr(motor_records):
    t, U, Y = motor_records
    res = run_batch(lugre.observer(second=False), t[:20], U[:, :20], Y[:, :20])
    assert isinstance(res[-1], EstimateResult) and res[-1].x_hat_refined is None
    assert res.ok and res.status == (Status.OK,) * 3 and res[0].failed_at is None
    assert res.x_hat.shape == (3, 20, 2) and not res.x_hat.flags.writeable
    assert "B=3, N=20" in repr(res)
    with pytest.raises(IndexError):
        res[3]


# --------------------------------------------------------------------------- one status
def test_a_failed_run_stops_alone_with_throw_false(motor_records):
    """Runs 0 and 2 converge, run 1 (unstable gains) diverges: with ``throw=False`` run 1
    stops with the status, step and rows of its own ``run(throw=False)``, the others are as
    if run alone; with ``throw=True`` the batch raises run 1's error."""
    t, U, Y = motor_records
    obs = [lugre.observer(eps=1.0), unstable_observer(lugre.observer(eps=1.0), 1e-3),
           lugre.observer(eps=0.5)]
    res = run_batch(obs, t, U, Y, throw=False)
    alone = [o.run(t, U[b], Y[b], throw=False) for b, o in enumerate(obs)]
    assert res.status == (Status.OK, Status.DIVERGED, Status.OK) and not res.ok
    bad = alone[1]
    assert bad.status == Status.DIVERGED and 0 < bad.failed_at < t.size
    assert res.failed_at == (None, bad.failed_at, None)
    assert res[1].message == bad.message.replace("in the step", "of run 1 in the step")
    assert np.isnan(res.x_hat[1, bad.failed_at:]).all()
    assert rel_err(res.x_hat[1, :bad.failed_at], bad.x_hat[:bad.failed_at]) <= BATCH_RTOL
    assert_matches(BatchObserverResult(t=res.t, x_hat=res.x_hat[::2], phi_hat=res.phi_hat[::2],
                                       theta_hat=res.theta_hat[::2],
                                       x_hat_refined=res.x_hat_refined[::2],
                                       skipped=res.skipped[::2]), alone[::2])
    assert "stopped=1" in repr(res)
    with pytest.raises(NonFiniteError, match=r"of run 1 in the step from t\[\d+\]"):
        run_batch(obs, t, U, Y)
