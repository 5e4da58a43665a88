"""One BLAS thread around the estimators (:mod:`thetahat.threads`), with threadpoolctl."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat.modelfile import load_model, run_estimator
from thetahat.modelfile.study import simulate_model
from thetahat.threads import one_blas_thread

threadpoolctl = pytest.importorskip("threadpoolctl")

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _blas_threads() -> set[int]:
    return {lib["num_threads"] for lib in threadpoolctl.threadpool_info()
            if lib["user_api"] == "blas"}


def test_the_block_runs_on_one_thread_and_gives_them_back():
    import scipy.linalg  # noqa: F401  (SciPy's own BLAS, when it has one, is limited too)
    before = threadpoolctl.threadpool_info()
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        outer = _blas_threads()
        with one_blas_thread():
            assert _blas_threads() == {1}
        assert _blas_threads() == outer          # nested: the outer setting is back
    assert threadpoolctl.threadpool_info() == before


@pytest.mark.parametrize("model", ["lugre", "prop3", "two_inertia", "heater"])
def test_run_estimator_runs_on_one_blas_thread(model):
    """Seen from inside the run: the progress callback asks threadpoolctl."""
    spec = load_model(EXAMPLES / f"{model}.toml")
    data = simulate_model(spec, seed=0, t_end=spec.scenario.t_end / 20)
    seen: list[set[int]] = []
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        res = run_estimator(spec, data.t, data.u, data.y, compiled=False, diagnose=False,
                            progress=lambda done, total: seen.append(_blas_threads()))
    assert seen and all(s == {1} for s in seen)
    assert np.all(np.isfinite(res.theta_hat))
