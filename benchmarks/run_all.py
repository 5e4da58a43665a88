"""Run every benchmark and write out/bench.json.

Run:  .venv/bin/python benchmarks/run_all.py [--quick] [--out out/bench.json]

* bench_lugre.py runs in this process (its estimators are timed side by side in one process);
  its results are the top level of out/bench.json: one entry per estimator (``thetahat_paper``,
  ``thetahat_best``, ``thetahat_guarded``, ``thetahat_mle``, ``ekf``, ``ukf``; null while
  unavailable) with the keys ``t_5pct``,
  ``t_1pct``, ``theta_rmse``, ``theta_bias``, ``omega_rmse``, ``eta_rmse``, ``rmse_over_crlb``,
  ``per_step_us``, ``diverged``, plus ``crlb`` and ``throughput``
  (``thetahat_steps_per_s``, ``solve_ivp_steps_per_s``). Non-finite values (a settling time
  that never happened) are written as null.
* bench_guarded.py (full run only; 20 seeds per scenario, the issue's) runs in this process
  (its estimators already compiled by bench_lugre's): the scenario table of the two-stage
  estimators against the EKF and the CRLB goes under ``guarded_scenarios``, with the cost
  comparison, and the figure to out/guarded_crlb.png. Its curves and table are also stored in
  benchmarks/results/guarded_crlb.json (committed): the site's gallery draws its figure from
  them, so ``make docs`` does not rerun the benchmark.
* ``--jobs`` (default: every core) forks that many worker processes over the independent
  records (seeds, robustness cases, grid points) of both; each record's estimators run one
  after the other in one process, and the cost comparisons run alone in this process.
* bench_estimate.py (``--quick``: 10⁵ samples) runs in this process: ``thetahat estimate`` on a
  10⁶-sample LuGre log (warm kernel cache), and the compiled vs Python per-sample cost of
  ``run_estimator``, under ``estimate``.
* bench_models.py (full run only; 4 seeds) runs in this process: every shipped model file by
  every method (paper, guarded, mle, JointEKF), RMSE ÷ √CRLB and median t1%.
* bench_emps.py runs in this process: each method on the measured EMPS record (warm cache)
  against the benchmark's own IDIM-LS, wall time and real-time factor.
* bench_cold_start.py (full run only: first compilations in fresh processes) runs in this
  process: the time of ``import thetahat`` and of ``thetahat estimate``'s first run of a model
  with an empty cache, on the C and on the numba back end, under ``cold_start``.
* bench_methods_step.py (full run only) runs in this process: µs per sample of every method
  (paper, guarded, mle, JointEKF) on each back end (Python, numba, C), under ``methods_step``
  (the README's table).
* bench_scb.py runs as a subprocess (n = 10, 50 with ``--quick``; its defaults otherwise); its
  rows go under ``scb``.
* bench_soak.py runs as a subprocess (10⁷ samples; 2·10⁵ with ``--quick``): the streaming
  soak's memory growth, θ̂ at the end and its checks go under ``soak``.

Tunings, grid scores and the per-case robustness results go to out/bench_details.json.
``--quick`` is meant to finish in under two minutes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_lugre
import metrics
import parallel

HERE = Path(__file__).resolve().parent
#: The stored results of bench_guarded's full run, which the gallery's figure is drawn from.
GUARDED_RESULTS = HERE / "results" / "guarded_crlb.json"
QUICK_BUDGET_S = 120.0
QUICK_SCB_SIZES = ("10", "50")
QUICK_SOAK_SAMPLES = 200_000


def run_scb(quick: bool) -> list:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scb.json"
        cmd = [sys.executable, str(HERE / "bench_scb.py"), "--json", str(path)]
        if quick:
            cmd += ["--sizes", *QUICK_SCB_SIZES]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        print(proc.stdout, end="")
        if proc.returncode != 0:
            print(f"bench_scb.py failed (exit {proc.returncode}):\n{proc.stderr}")
            return []
        return json.loads(path.read_text())


def run_soak(quick: bool) -> dict | None:
    """bench_soak.py in a fresh interpreter (its memory figures must not include ours)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "soak.json"
        cmd = [sys.executable, str(HERE / "bench_soak.py"), "--json", str(path)]
        if quick:
            cmd += ["--samples", str(QUICK_SOAK_SAMPLES)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        print(proc.stdout, end="")
        if not path.exists():
            print(f"bench_soak.py failed (exit {proc.returncode}):\n{proc.stderr}")
            return None
        if proc.returncode != 0:
            print("bench_soak.py: a soak check FAILED (see above)")
        return json.loads(path.read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("out/bench.json"))
    ap.add_argument("--jobs", type=int, default=parallel.default_jobs(),
                    help="worker processes over independent records (default: every core)")
    args = ap.parse_args()
    jobs = ["--jobs", str(args.jobs)]
    t0 = time.perf_counter()
    print("=== bench_lugre.py" + (" --quick" if args.quick else ""))
    lugre = bench_lugre.main((["--quick"] if args.quick else []) + jobs)
    print("\n=== bench_scb.py" + (f" --sizes {' '.join(QUICK_SCB_SIZES)}" if args.quick else ""))
    scb = run_scb(args.quick)
    payload = dict(lugre["payload"])
    payload["scb"] = scb
    import bench_estimate
    print("\n=== bench_estimate.py" + (" --samples 100000" if args.quick else ""))
    payload["estimate"] = bench_estimate.main(
        ["--samples", "100000", "--python-samples", "5000"] if args.quick else [])
    import bench_emps
    print("\n=== bench_emps.py")
    payload["emps"] = bench_emps.main([])
    if not args.quick:
        import bench_guarded
        print("\n=== bench_guarded.py")
        payload["guarded_scenarios"] = bench_guarded.main(
            ["--seeds", "20", "--figure", str(args.out.with_name("guarded_crlb.png")),
             "--results", str(GUARDED_RESULTS), "--no-models", *jobs])
        import bench_models
        print("\n=== bench_models.py")
        payload["models"] = bench_models.main(["--seeds", "4"])
        import bench_cold_start
        print("\n=== bench_cold_start.py")
        payload["cold_start"] = bench_cold_start.main([])
        import bench_methods_step
        print("\n=== bench_methods_step.py")
        payload["methods_step"] = bench_methods_step.main([])
    print("\n=== bench_soak.py" + (f" --samples {QUICK_SOAK_SAMPLES}" if args.quick else ""))
    payload["soak"] = run_soak(args.quick)
    details = dict(lugre["details"])
    wall = time.perf_counter() - t0
    details["run_all_wall_s"] = wall
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(metrics.jsonable(payload), indent=2))
    args.out.with_name(args.out.stem + "_details.json").write_text(
        json.dumps(metrics.jsonable(details), indent=2))
    print(f"\nwrote {args.out} and {args.out.stem}_details.json; total {wall:.0f} s")
    if args.quick and wall > QUICK_BUDGET_S:
        print(f"warning: --quick took {wall:.0f} s, over its {QUICK_BUDGET_S:.0f} s budget")


if __name__ == "__main__":
    main()
