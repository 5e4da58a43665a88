"""Throughput of the distributed engine: in this process vs a local Dask cluster.

Run:  OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_dask.py [--files 64] [--workers 2]

Same work both ways, timed in one run: (1) a fleet of generated records of the Proposition 3
oscillator (examples/prop3.toml) through ``estimate_many``; (2) a Monte-Carlo of the
two-inertia drive (simulate + estimate per seed) through ``monte_carlo``. Prints runs/s and the
ratio cluster / in-process. The cluster is a ``LocalCluster`` of worker processes on loopback
(one thread each), started before timing; its start-up cost is printed separately. On a shared
2-core machine the ratio is bounded by 2 and by what else runs.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")        # one BLAS thread per process
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from thetahat.fleet import estimate_many  # noqa: E402
from thetahat.models import prop3_monotone as p3  # noqa: E402
from thetahat.models import two_inertia as ti  # noqa: E402
from thetahat.simulation.batch import monte_carlo  # noqa: E402

MODEL = Path(__file__).resolve().parents[1] / "examples" / "prop3.toml"


def write_fleet(directory: Path, n: int) -> None:
    for i in range(n):
        tr = p3.simulate(seed=i, theta=[-1.6 + 3.2 * (i % 13) / 12], t_end=20.0, fs=20.0,
                         noise_std=0.002)
        np.savetxt(directory / f"m{i:03d}.csv", np.c_[tr.t, tr.u, tr.y], delimiter=",",
                   header="t,u,y", comments="", fmt="%.17g")


def drive_run(seed: int) -> float:
    """One Monte-Carlo run of the two-inertia drive: θ̂_F_m at the end of a 2 s record."""
    tr = ti.simulate(seed=seed, t_end=2.0)
    return float(ti.observer().run(tr.t, tr.u, tr.y).theta_hat[-1, 0])


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=64)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    from dask.distributed import Client, LocalCluster

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        write_fleet(d, args.files)
        t0 = time.perf_counter()
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                          host="127.0.0.1", dashboard_address=None,
                          env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}) as lc, \
                Client(lc) as client:
            client.wait_for_workers(args.workers)
            # Warm-up (not timed): imports, the parsed model and the lambdified g in each
            # worker, as this process has them after writing the fleet.
            files = sorted(d.iterdir())
            estimate_many(MODEL, files[:2 * args.workers], chunk_size=1, progress=False,
                          scheduler=client)
            monte_carlo(drive_run, range(args.workers), scheduler=client, chunk_size=1,
                        progress=False)
            drive_run(0)
            print(f"cluster start-up and warm-up ({args.workers} workers): "
                  f"{time.perf_counter() - t0:.1f} s; load average {os.getloadavg()[0]:.1f} "
                  f"on {os.cpu_count()} cores")
            chunk = max(1, args.files // (4 * args.workers))
            here, t_here = timed(lambda: estimate_many(MODEL, d, chunk_size=chunk,
                                                       progress=False))
            there, t_there = timed(lambda: estimate_many(MODEL, d, chunk_size=chunk,
                                                         progress=False, scheduler=client))
            same = np.array_equal(here.theta_hat(), there.theta_hat())
            print(f"fleet of {args.files} records (20 s at 20 Hz, {chunk} per task): "
                  f"in-process {args.files / t_here:.1f} files/s, cluster "
                  f"{args.files / t_there:.1f} files/s, ratio {t_here / t_there:.2f}x, "
                  f"identical: {same}")
            seeds = range(args.seeds)
            mc_here, m_here = timed(lambda: monte_carlo(drive_run, seeds, progress=False))
            mc_there, m_there = timed(lambda: monte_carlo(drive_run, seeds, scheduler=client,
                                                          chunk_size=1, progress=False))
            print(f"Monte-Carlo of the two-inertia drive ({args.seeds} runs of 2 s at 1 kHz): "
                  f"in-process {args.seeds / m_here:.2f} runs/s, cluster "
                  f"{args.seeds / m_there:.2f} runs/s, ratio {m_here / m_there:.2f}x, "
                  f"identical: {mc_here.results == mc_there.results}")


if __name__ == "__main__":
    main()
