"""``thetahat estimate`` on a long LuGre log: the compiled observer against the Python one.

Run:  .venv/bin/python benchmarks/bench_estimate.py [--samples 1000000] [--python-samples 20000]

A log of ``--samples`` samples at 1 kHz (the paper's DC motor, examples/lugre.toml: the 20 s
default scenario simulated once and repeated end to end, so the record is as hard as the
scenario throughout) is written as CSV and estimated by the CLI in a fresh process, twice: the
first run fills the kernel cache (the model's first compilation), the second is the warm-cache
wall time the target (≤ 10 s for 10⁶ samples, progress shown) refers to, with the time of each
of its stages (the command's final line: load model, read, estimate, trust report, write) and
its ratio to ``numpy.loadtxt`` of the same CSV (the issue's aim: ≤ 10×), for each of
``--methods`` (default paper, guarded and mle: the issue's target is each). In this process the
same record goes through ``run_estimator`` compiled, and a prefix of ``--python-samples``
through the Python observer (6 min for 10⁶ samples: its per-sample cost is what is compared).
Printed: the CLI's wall times, both per-sample costs and their ratio, all from one run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MODEL = HERE.parent / "examples" / "lugre.toml"


def lugre_log(samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, u, y) of ``samples`` samples at 1 kHz: the default scenario, repeated."""
    from thetahat.models import lugre
    run = lugre.simulate(seed=0)
    reps = -(-samples // run.t.size)
    dt = float(run.t[1] - run.t[0])
    t = np.arange(samples) * dt
    u = np.tile(run.u.reshape(-1), reps)[:samples]
    y = np.tile(run.y.reshape(-1), reps)[:samples]
    return t, u, y


def cli_wall(data: Path, out: Path, env: dict[str, str], method: str = "paper"
             ) -> tuple[float, str]:
    """The command's wall time and its final line (the time of each stage)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "thetahat", "estimate", str(MODEL), str(data),
                           "-o", str(out), "--method", method], env=env, check=True,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    final = [line for line in proc.stderr.splitlines() if line.startswith("thetahat: done")]
    return time.perf_counter() - t0, final[-1] if final else ""


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--python-samples", type=int, default=20_000)
    ap.add_argument("--methods", nargs="+", default=["paper", "guarded", "mle"],
                    help="the methods the CLI runs (default: paper guarded mle)")
    args = ap.parse_args(argv)
    from thetahat.modelfile import load_model, run_estimator
    spec = load_model(MODEL)
    t, u, y = lugre_log(args.samples)
    with tempfile.TemporaryDirectory() as tmp:
        data, out = Path(tmp) / "log.csv", Path(tmp) / "estimates.csv"
        from thetahat.io.datafile import write_csv_table
        write_csv_table(data, {"t": t, "u": u, "y": y})
        t0 = time.perf_counter()
        np.loadtxt(data, delimiter=",", skiprows=1)
        parse = time.perf_counter() - t0
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        cli = {}
        for method in args.methods:
            first_m, _ = cli_wall(data, out, env, method)
            cli[method] = (first_m, *cli_wall(data, out, env, method))
        first, warm, stages = cli.get("paper", next(iter(cli.values())))
    t0 = time.perf_counter()
    fast = run_estimator(spec, t, u[:, None], y[:, None], compiled=True, method="paper")
    fast_s = time.perf_counter() - t0
    n_py = min(args.python_samples, args.samples)
    t0 = time.perf_counter()
    slow = run_estimator(spec, t[:n_py], u[:n_py, None], y[:n_py, None], compiled=False,
                         method="paper")
    python_s = time.perf_counter() - t0
    agree = float(np.max(np.abs(fast.theta_hat[:n_py] - slow.theta_hat)))
    per_fast, per_py = fast_s / args.samples, python_s / n_py
    print(f"thetahat estimate, {args.samples} LuGre samples; numpy.loadtxt of the CSV "
          f"{parse:.2f} s")
    for method, (first_m, warm_m, stages_m) in cli.items():
        print(f"  --method {method}: {warm_m:.1f} s wall with a warm kernel cache (first run "
              f"{first_m:.1f} s): ratio to the parse {warm_m / parse:.1f}× (aim ≤ 10×)")
        print(f"    its stages: {stages_m.removeprefix('thetahat: ')}")
    print(f"run_estimator: compiled {per_fast * 1e6:.2f} µs/sample, Python "
          f"{per_py * 1e6:.0f} µs/sample ({n_py} samples): ratio {per_py / per_fast:.0f}×; "
          f"max |Δθ̂| {agree:.1e}")
    return {"samples": args.samples, "cli_warm_s": warm, "cli_first_s": first,
            "cli": {m: {"first_s": v[0], "warm_s": v[1], "stages": v[2], "over_loadtxt":
                        v[1] / parse} for m, v in cli.items()},
            "loadtxt_s": parse, "cli_over_loadtxt": warm / parse, "cli_stages": stages,
            "compiled_us_per_sample": per_fast * 1e6, "python_us_per_sample": per_py * 1e6,
            "ratio": per_py / per_fast, "max_theta_diff": agree}


if __name__ == "__main__":
    json.dumps(main())
