"""(ε, Γ) tuning (Sec. VII): the choice minimises the score, diverged pairs are rejected."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.errors import DesignError
from thetahat.models import lugre
from thetahat.studies.tune import TuneResult, tune_eps_gamma

#: Short record: long enough for θ̂ to approach θ = 0.28 from 0.5 (the default scenario's
#: excitation |φ̂| >= 1 recurs every ~1 s), short enough to keep the file under 20 s.
T_END = 4.0
#: ε = 0.001 gives K ~ ε^-3 ~ 1e9 at 1 kHz: the discretised observer explodes at once.
EPS_DIVERGING = 0.001
#: A stable run's θ RMSE over the second half is far below |θ̂(0) − θ| = 0.22.
THETA_RMSE_BOUND = 0.1

SIM = functools.partial(lugre.simulate, t_end=T_END)
THETA_HAT0 = [lugre.Scenario().theta_hat0]


@pytest.fixture(scope="module")
def stable_grid() -> TuneResult:
    return tune_eps_gamma(lugre.observer, SIM, eps_values=[1.0, 0.5], gammas=[1.0, 10.0],
                          seeds=[1000], theta_hat0=THETA_HAT0)


def test_choice_minimises_the_recorded_score(stable_grid):
    res = stable_grid
    assert res.score.shape == (2, 2)
    assert not res.diverged.any()
    np.testing.assert_array_equal(res.score, res.theta_rmse.max(axis=2))
    i, j = res.eps.index(res.best_eps), res.Gamma.index(res.best_Gamma)
    assert res.score[i, j] <= 1.05 * res.score.min()           # within rel_tol of the best
    # and it is the near-tie with the largest ε, then the smallest Γ
    near = np.argwhere(res.score <= 1.05 * res.score.min())
    assert (i, j) == tuple(near[0])
    assert res.score.max() < THETA_RMSE_BOUND
    assert np.isfinite(res.x_rmse).all() and res.x_rmse.shape == (2, 2, 1, 2)
    table = res.table(("omega", "eta"))
    assert "<- chosen" in table and f"eps = {res.best_eps:g}" in table


def test_batched_runs_match_single_runs(stable_grid):
    data = SIM(1000)
    obs = lugre.observer(0.5, Gamma=10.0)
    one = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=THETA_HAT0))
    err = one.theta_hat[one.t.size // 2:, 0] - data.theta[0]
    assert stable_grid.theta_rmse[1, 1, 0] == pytest.approx(np.sqrt(np.mean(err ** 2)),
                                                            rel=1e-8)


def test_diverging_eps_is_marked_and_never_chosen():
    res = tune_eps_gamma(lugre.observer, SIM, eps_values=[1.0, EPS_DIVERGING],
                         gammas=[1.0, 10.0], seeds=[1000], theta_hat0=THETA_HAT0)
    assert res.diverged[1].all() and not res.diverged[0].any()
    assert np.isinf(res.score[1]).all()
    assert res.best_eps == 1.0
    # every diverged run is reported with its pair and seed, whatever form the divergence took
    # (a raised NonFiniteError, an inf or an overflow: that depends on the numpy version)
    assert len(res.errors) == int(res.diverged.sum()) == 2
    for gamma, err in zip((1.0, 10.0), res.errors):
        assert f"eps={EPS_DIVERGING:g}, Gamma={gamma:g}, seed=1000:" in err, err
    assert "diverged" in res.table()


def test_every_pair_diverging_gives_no_choice():
    stub = TuneResult(eps=(1.0,), Gamma=(1.0,), seeds=(0,), criterion="theta_rmse",
                      diverged=np.ones((1, 1, 1), bool), theta_rmse=np.full((1, 1, 1), np.nan),
                      t_1pct=np.full((1, 1, 1), np.nan), x_rmse=np.full((1, 1, 1, 2), np.nan),
                      score=np.full((1, 1), np.inf), best_eps=None, best_Gamma=None,
                      errors=(), wall_time=0.0)
    assert "no (eps, Gamma) pair" in stub.verdict()
    assert json.dumps(stub.to_dict())


@pytest.mark.parametrize("kwargs, match", [
    ({"eps_values": [0.5, 0.3]}, "start at 1"),
    ({"gammas": [1.0, -1.0]}, "gammas must be finite, > 0"),
    ({"gammas": [10.0, 1.0]}, "strictly increasing"),
    ({"criterion": "x_rmse"}, "criterion must be one of"),
])
def test_bad_settings_raise(kwargs, match):
    with pytest.raises(DesignError, match=match):
        tune_eps_gamma(lugre.observer, SIM, theta_hat0=THETA_HAT0, **kwargs)


def test_cli_tune_writes_json(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["tune", "--eps", "1", "0.5", "--gamma", "1", "10", "--seeds", "1000",
                 "--t-end", str(T_END), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "chosen: eps =" in printed
    summary = json.loads((out / "tune.json").read_text())
    assert summary["eps"] == [1.0, 0.5] and summary["Gamma"] == [1.0, 10.0]
    assert summary["best_eps"] in (1.0, 0.5) and summary["best_Gamma"] in (1.0, 10.0)


def test_cli_tune_rejects_bad_eps(capsys):
    assert main(["tune", "--eps", "0.5", "0.3", "--t-end", "0.5"]) == 2
    assert "thetahat: error:" in capsys.readouterr().err


def test_zero_tolerance_picks_the_exact_minimum():
    res = tune_eps_gamma(lugre.observer, SIM, eps_values=[1.0, 0.5], gammas=[1.0, 10.0],
                         seeds=[1000], theta_hat0=THETA_HAT0, rel_tol=0.0)
    i, j = res.eps.index(res.best_eps), res.Gamma.index(res.best_Gamma)
    assert res.score[i, j] == res.score.min()


def test_worker_processes_give_the_same_grid(stable_grid):
    """Each ε is one engine task; in two worker processes the scores and the choice are
    those computed here (same computation per task: equal to round-off, 1e-12 relative)."""
    res = tune_eps_gamma(lugre.observer, SIM, eps_values=[1.0, 0.5], gammas=[1.0, 10.0],
                         seeds=[1000], theta_hat0=THETA_HAT0, n_jobs=2)
    np.testing.assert_allclose(res.score, stable_grid.score, rtol=1e-12)
    assert (res.best_eps, res.best_Gamma) == (stable_grid.best_eps, stable_grid.best_Gamma)


def test_long_records_run_each_pair_on_the_fastest_back_end(stable_grid, monkeypatch):
    """At COMPILE_MIN_SAMPLES samples and beyond, each (ε, Γ, seed) runs on its compiled form
    (the C of the formulas or numba), not in the NumPy batch: the same scores, to rounding."""
    import dataclasses

    from thetahat.codegen.native import native_enabled
    import thetahat.estimation.drive as drive
    if not native_enabled():
        pytest.importorskip("numba", reason="no C compiler and no numba: nothing compiled")
    real, used = drive.runner, []

    def spy(obs, t, **kw):
        fast = real(obs, t, **kw)
        used.append(fast is not obs)
        return fast

    monkeypatch.setattr(drive, "COMPILE_MIN_SAMPLES", 1000)      # the 4 000-sample records
    monkeypatch.setattr(drive, "runner", spy)
    numba = next((b for b in drive.backends() if b.name == "numba"), None)
    if numba is not None:
        drive.register(dataclasses.replace(numba, min_samples=1000))
    try:
        res = tune_eps_gamma(lugre.observer, SIM, eps_values=[1.0, 0.5], gammas=[1.0, 10.0],
                             seeds=[1000], theta_hat0=THETA_HAT0)
    finally:
        if numba is not None:
            drive.register(numba)
    assert len(used) == 4 and all(used)                        # 2 ε × 2 Γ × 1 seed, compiled
    # the compiled step is the NumPy step's formulas: agreement far below the scores' spread
    np.testing.assert_allclose(res.theta_rmse, stable_grid.theta_rmse, rtol=1e-6)


def test_no_pair_that_converged_means_no_choice_and_a_warning(capsys, tmp_path):
    """Γ = 1 on the 4 s LuGre record: θ̂ never settles within 1 % of θ (t_1% = inf on every
    pair), so none is chosen — not the smallest RMSE among failures — a ThetahatWarning says
    so, and the command exits with status 2."""
    from thetahat.errors import ThetahatWarning
    with pytest.warns(ThetahatWarning, match="no \\(eps, Gamma\\) pair converged"):
        res = tune_eps_gamma(lugre.observer, SIM, eps_values=[1.0, 0.5], gammas=[1.0],
                             seeds=[1000], theta_hat0=THETA_HAT0)
    assert np.isinf(res.t_1pct).all() and not res.rejected.any()       # the premise
    assert not res.converged.any()
    assert res.best_eps is None and res.best_Gamma is None
    assert "none is chosen" in res.verdict() and "<- chosen" not in res.table()
    assert main(["tune", "--eps", "1", "0.5", "--gamma", "1", "--seeds", "1000",
                 "--t-end", str(T_END), "--out", str(tmp_path / "o")]) == 2
    assert "no (eps, Gamma) pair converged" in capsys.readouterr().err


def test_a_pair_that_did_not_settle_is_never_chosen(stable_grid):
    """Among the stable grid's pairs only those whose θ̂ settled on every seed are candidates:
    the choice has a finite t_1%."""
    i, j = stable_grid.eps.index(stable_grid.best_eps), stable_grid.Gamma.index(
        stable_grid.best_Gamma)
    assert stable_grid.converged[i, j] and np.isfinite(stable_grid.t_1pct[i, j]).all()


@pytest.mark.slow
def test_tune_on_the_newcomers_stribeck_model_picks_nothing():
    """examples/stribeck.toml (θ = (F_c, F_s, v_s)), 2 s of its scenario: no (ε, Γ) settles
    within 1 %, and tune says so instead of choosing (the issue: it chose ε = 1, Γ = 30)."""
    from pathlib import Path
    from thetahat.errors import ThetahatWarning
    from thetahat.modelfile import load_model
    from thetahat.modelfile.study import study_setup
    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / "stribeck.toml")
    setup = study_setup(spec, t_end=2.0)
    with pytest.warns(ThetahatWarning, match="no \\(eps, Gamma\\) pair converged"):
        res = tune_eps_gamma(setup.estimator, setup.simulate, eps_values=[1.0],
                             gammas=[30.0], seeds=[1000], theta_hat0=setup.theta_hat0)
    assert res.best_eps is None and not res.converged.any()
