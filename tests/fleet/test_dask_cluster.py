"""The engine on a real Dask cluster: a LocalCluster of 2 worker processes on loopback.

Same fleet, same Monte-Carlo, same numbers as in this process; a worker killed in the middle of
a run loses and duplicates nothing (the scheduler re-runs its tasks; results are keyed by file
and seed)."""

import functools
import os
import signal
import threading
import time

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from fleet_data import CORRUPT, MODEL, N_FILES  # noqa: E402

from thetahat.engine import run_keyed  # noqa: E402
from thetahat.fleet import estimate_many  # noqa: E402
from thetahat.models import prop3_monotone as p3  # noqa: E402
from thetahat.studies.batch import monte_carlo  # noqa: E402

# The chunks are the same in both runs, and each chunk is the same computation: the numbers
# are bitwise equal (no tolerance).


@pytest.fixture(scope="module")
def cluster():
    from dask.distributed import Client, LocalCluster

    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, env=env) as lc, Client(lc) as client:
        client.wait_for_workers(2, timeout=60)
        yield lc, client


#: Agreement of one record's θ̂ computed in this process and in a worker (see below).
SAME_RUN_RTOL = 1e-12


def test_fleet_same_rows_in_process_and_on_the_cluster(cluster, fleet_dir, fleet):
    lc, client = cluster
    here = fleet
    there = estimate_many(MODEL, fleet_dir, chunk_size=8, progress=False,
                          scheduler=lc.scheduler_address)        # by address, as the CLI does
    assert len(there.rows) == N_FILES and there.n_ok == N_FILES - 1
    assert list(there.failed) == list(here.failed) and next(iter(there.failed)).endswith(CORRUPT)
    for a, b in zip(here.rows, there.rows):
        assert a.keys() == b.keys()
        for k in a:
            if isinstance(a[k], float) and isinstance(b[k], float):
                # the same computation in a worker process, whose BLAS may take another kernel:
                # equal to the last bits (bitwise with the locked versions; 1 ulp seen with
                # numpy 1.26), far below any statistical meaning of θ̂
                assert a[k] == b[k] or (a[k] != a[k] and b[k] != b[k]) or \
                    abs(a[k] - b[k]) <= SAME_RUN_RTOL * abs(a[k]), (k, a[k], b[k])
            else:
                assert a[k] == b[k], (k, a[k], b[k])


def _mc_run(seed):
    """One Monte-Carlo run: a noisy record of the oscillator, θ̂ at its end."""
    from thetahat.modelfile import build_observer, load_model

    tr = p3.simulate(seed=seed, t_end=6.0, fs=20.0)
    return float(build_observer(load_model(MODEL)).run(tr.t, tr.u, tr.y).theta_hat[-1, 0])


def test_monte_carlo_same_results_on_the_cluster(cluster):
    _, client = cluster
    seeds = range(12)
    here = monte_carlo(_mc_run, seeds, progress=False)
    there = monte_carlo(_mc_run, seeds, scheduler=client, chunk_size=3, progress=False)
    assert there.seeds == here.seeds
    assert there.results == here.results                      # bitwise


def _slow_chunk(items, *, delay):
    time.sleep(delay)
    return [(i, (i, os.getpid())) for i in items]


def test_worker_killed_mid_run_loses_and_duplicates_nothing(cluster):
    """SIGKILL one worker process while tasks run: its tasks are re-run elsewhere; every key
    comes back exactly once with the right value."""
    lc, client = cluster
    pids = list(client.run(os.getpid).values())
    assert len(pids) == 2
    killed = {}

    def kill_when_started():
        deadline = time.time() + 60
        while time.time() < deadline:
            done = client.run_on_scheduler(
                lambda dask_scheduler: sum(ts.state == "memory"
                                           for ts in dask_scheduler.tasks.values()))
            if done >= 2:
                killed["pid"], killed["done"] = pids[0], done
                os.kill(pids[0], signal.SIGKILL)
                return
            time.sleep(0.05)

    items = list(range(40))
    killer = threading.Thread(target=kill_when_started)
    killer.start()
    out = run_keyed(functools.partial(_slow_chunk, delay=0.4), items, items, scheduler=client,
                    chunk_size=2, label="kill-test", progress=False)
    killer.join()
    assert "pid" in killed and killed["done"] < 20            # killed in the middle of the run
    assert list(out) == items and [v[0] for v in out.values()] == items
    survivors = {v[1] for v in out.values()}
    assert pids[1] in survivors                               # the other worker took over
    client.wait_for_workers(2, timeout=60)                    # the nanny restarts the dead one


@pytest.mark.slow
def test_fleet_with_a_worker_killed(cluster, fleet_dir):
    """The acceptance run: the fleet of 52 files with a worker killed in the middle gives the
    same rows as in this process (~25 s; the fast variant above kills a worker during a
    keyed run of sleeping tasks)."""
    lc, client = cluster
    here = estimate_many(MODEL, fleet_dir, chunk_size=2, progress=False)
    pids = list(client.run(os.getpid).values())
    t_kill = {}

    def kill():
        t_kill["t"] = time.perf_counter()
        os.kill(pids[-1], signal.SIGKILL)

    timer = threading.Timer(2.0, kill)
    start = time.perf_counter()
    timer.start()
    there = estimate_many(MODEL, fleet_dir, chunk_size=2, progress=False, scheduler=client)
    done = time.perf_counter()
    timer.join()
    assert start < t_kill["t"] < done                         # killed while the fleet ran
    assert [r["file"] for r in there.rows] == [r["file"] for r in here.rows]
    np.testing.assert_array_equal(there.theta_hat(), here.theta_hat())
    assert there.failed == here.failed
    client.wait_for_workers(2, timeout=60)


def _p3_observer(eps):
    from thetahat import ModifiedHighGainObserver, modified_high_gain

    sys_ = p3.system()
    d = modified_high_gain(sys_.A, sys_.E, sys_.C, eps)
    return ModifiedHighGainObserver.from_design(sys_, d, p3.update_law())


def _p3_simulate(seed):
    return p3.simulate(seed=seed, t_end=6.0, fs=20.0)


def test_eps_sweep_same_table_on_the_cluster(cluster):
    from thetahat.studies.sweep import eps_sweep

    _, client = cluster
    args = (_p3_observer, _p3_simulate, [1.0, 0.5], range(3))
    here = eps_sweep(*args, theta_hat0=[0.0], progress=False)
    there = eps_sweep(*args, theta_hat0=[0.0], progress=False, scheduler=client)
    a, b = here.to_dict(), there.to_dict()
    a.pop("wall_time_s"), b.pop("wall_time_s")
    assert b == a


def test_tune_same_choice_on_the_cluster(cluster):
    """The tuner's ε tasks run on the engine: the same grid of scores and the same (ε, Γ)."""
    from thetahat.studies.tune import tune_eps_gamma

    _, client = cluster
    kw = dict(eps_values=[1.0, 0.5], gammas=[1.0, 4.0], seeds=[0, 1], theta_hat0=[0.0])
    here = tune_eps_gamma(_p3_observer_gamma, _p3_simulate, **kw)
    there = tune_eps_gamma(_p3_observer_gamma, _p3_simulate, **kw, scheduler=client)
    a, b = here.to_dict(), there.to_dict()
    a.pop("wall_time_s"), b.pop("wall_time_s")
    _assert_same_run(a, b)
    assert (there.best_eps, there.best_Gamma) == (here.best_eps, here.best_Gamma)
    assert here.best_eps is not None


def _assert_same_run(a, b, where="result"):
    """Equal structure and values; floats to SAME_RUN_RTOL: the tuner's batch of Γ × seeds
    goes through matmul, whose BLAS kernel may differ in a worker (1 ulp seen, numpy 1.26)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_same_run(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same_run(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert a == b or (a != a and b != b) or abs(a - b) <= SAME_RUN_RTOL * abs(a), \
            (where, a, b)
    else:
        assert a == b, (where, a, b)


def _p3_observer_gamma(eps, Gamma=2.0):
    from thetahat import ModifiedHighGainObserver, modified_high_gain

    sys_ = p3.system()
    d = modified_high_gain(sys_.A, sys_.E, sys_.C, eps)
    return ModifiedHighGainObserver.from_design(sys_, d, p3.update_law(Gamma))
