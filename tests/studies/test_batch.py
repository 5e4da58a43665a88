"""Monte-Carlo batches: seed order, parallel == sequential, progress bar, errors."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from thetahat.errors import DimensionError, ThetahatWarning
from thetahat.models import lugre
from thetahat.studies import batch as batch_module
from thetahat.studies.batch import BatchResult, monte_carlo
from thetahat.simulation.noise import WhiteNoise, make_rng


def noise_summary(seed: int, n: int = 500) -> np.ndarray:
    """A cheap, picklable run: statistics of one seeded noise draw."""
    e = WhiteNoise(0.02).sample(make_rng(seed), n, 1, 1000.0)
    return np.array([e.mean(), e.std(), e[0, 0]])


def fails_on_three(seed: int) -> int:
    if seed == 3:
        raise ArithmeticError(f"run {seed} failed")
    return seed


def test_results_follow_seed_order():
    seeds = [7, 2, 5, 0]
    res = monte_carlo(noise_summary, seeds, progress=False)
    assert res.seeds == (7, 2, 5, 0) and len(res) == 4 and res.n_jobs == 1
    for s, r in zip(seeds, res):
        np.testing.assert_array_equal(r, noise_summary(s))
    stacked = res.stack()
    assert stacked.shape == (4, 3)
    assert len({row[2] for row in stacked}) == 4       # different seeds, different data


def test_parallel_equals_sequential():
    seeds = list(range(10, 0, -1))
    seq = monte_carlo(noise_summary, seeds, progress=False)
    par = monte_carlo(noise_summary, seeds, progress=False, n_jobs=2)
    assert par.n_jobs == 2 and par.seeds == seq.seeds
    np.testing.assert_array_equal(par.stack(), seq.stack())


def test_parallel_lugre_runs_equal_sequential():
    fn = functools.partial(lugre.simulate, t_end=0.2)
    seq = monte_carlo(fn, [1, 0], progress=False)
    par = monte_carlo(fn, [1, 0], progress=False, n_jobs=2)
    np.testing.assert_array_equal(par.stack("y"), seq.stack("y"))
    np.testing.assert_array_equal(par.stack("x"), seq.stack("x"))
    assert not np.array_equal(seq[0].y, seq[1].y)
    np.testing.assert_array_equal(seq[0].x, seq[1].x)    # noise seed only changes y


def test_stack_attribute_and_ragged_error():
    res = monte_carlo(lambda s: np.zeros(s + 1), [0, 1], progress=False)
    with pytest.raises(DimensionError, match="cannot stack"):
        res.stack()
    with pytest.raises(AttributeError):
        res.stack("no_such_attribute")


@pytest.mark.parametrize("n_jobs", [1, 2])
def test_first_failure_in_seed_order_propagates(n_jobs):
    with pytest.raises(ArithmeticError, match="run 3 failed"):
        monte_carlo(fails_on_three, [1, 3, 5], progress=False, n_jobs=n_jobs)


@pytest.mark.parametrize("seeds, n_jobs, match", [
    ([], 1, "at least one"),
    ([1, -2], 1, "non-negative"),
    ([1.5], 1, "non-negative"),
    ([1], 0, "n_jobs"),
    ([1], -3, "n_jobs"),
])
def test_argument_errors(seeds, n_jobs, match):
    with pytest.raises(DimensionError, match=match):
        monte_carlo(noise_summary, seeds, progress=False, n_jobs=n_jobs)


def test_unpicklable_fn_rejected_for_parallel_runs():
    with pytest.raises(TypeError, match="picklable"):
        monte_carlo(lambda s: s, [1, 2], progress=False, n_jobs=2)
    assert monte_carlo(lambda s: s, [1, 2], progress=False).results == (1, 2)


def test_duplicate_seeds_warn():
    with pytest.warns(ThetahatWarning, match="duplicates"):
        monte_carlo(noise_summary, [1, 1], progress=False)


def test_progress_bar_only_for_long_batches(capsys, monkeypatch):
    pytest.importorskip("tqdm")
    monte_carlo(noise_summary, range(3), progress=True)
    assert "monte_carlo" not in capsys.readouterr().err       # quick: no bar
    monkeypatch.setattr(batch_module, "PROGRESS_DELAY_S", 0.0)
    monte_carlo(noise_summary, range(3), progress=True)
    assert "monte_carlo" in capsys.readouterr().err           # "long" batch: bar shown
    monte_carlo(noise_summary, range(3), progress=False)
    assert "monte_carlo" not in capsys.readouterr().err


def test_batch_result_is_frozen_with_readable_repr():
    res = monte_carlo(noise_summary, range(8), progress=False)
    assert isinstance(res, BatchResult)
    assert "n_runs=8" in repr(res) and "..., 7]" in repr(res)
    with pytest.raises(AttributeError):
        res.results = ()  # type: ignore[misc]
