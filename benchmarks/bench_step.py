"""Per-step cost of the observer's back ends on the paper's DC motor (Sec. VIII), optionally
against another source tree of thetahat measured in the same run.

Run:  .venv/bin/python benchmarks/bench_step.py [--t-end 2] [--against OTHER/src] [--rounds 3]

Paths (all with the second observer, ZOH, 1 kHz, ε = 1, Γ = 1):

* ``step``: a Python loop of ``ModifiedHighGainObserver.step`` (µs per call);
* ``run``: ``ModifiedHighGainObserver.run`` (µs per sample);
* ``batch``: ``run_batch`` over BATCH_SIZE seeds (µs per observer-step, i.e. per sample per run);
* ``compiled``: ``CompiledObserver.run`` (µs per sample, loop in numba; skipped without numba).

Times are CPU times of the process (``time.process_time``, best of a few repetitions), which a
shared machine disturbs less than wall time; run with ``OPENBLAS_NUM_THREADS=1`` there (BLAS
threads fighting over busy cores made a 15×15 ``expm`` 1000× slower in our measurements).
With ``--against``, each round measures this tree and the other one in two fresh processes
(alternating, so both see the same machine load) and prints the ratios ours ÷ other of the
median and of the best time per path over the rounds: < 1 means this tree is faster.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

BATCH_SIZE = 20

_MEASURE = r"""
import json, sys, time
import numpy as np
from thetahat.models import lugre
t_end = float(sys.argv[1]); B = int(sys.argv[2])
trajs = [lugre.simulate(seed=s, t_end=t_end) for s in range(B)]
tr = trajs[0]
obs = lugre.observer()
s0 = obs.init(theta_hat0=[0.5])
N = tr.t.size
dt = float(tr.t[1] - tr.t[0])
out = {}
def best(fn, reps=3):
    b = float("inf")
    for _ in range(reps):
        t0 = time.process_time(); fn(); b = min(b, time.process_time() - t0)
    return b
def loop():
    s = s0
    for k in range(N - 1):
        s = obs.step(s, tr.u[k], tr.y[k], dt)
obs.step(s0, tr.u[0], tr.y[0], dt)
out["step"] = 1e6 * best(loop) / (N - 1)
out["run"] = 1e6 * best(lambda: obs.run(tr.t, tr.u, tr.y, state0=s0)) / N
from thetahat.estimation.observer.batch_run import run_batch
U = np.stack([t.u for t in trajs]); Y = np.stack([t.y for t in trajs])
out["batch"] = 1e6 * best(lambda: run_batch(obs, tr.t, U, Y, state0=s0)) / (B * N)
try:
    import numba  # noqa: F401
    from thetahat.estimation.observer.compiled import compile_observer
except ImportError:
    pass
else:
    try:                      # θ* carries its SymPy form
        fast = compile_observer(obs, dt=dt)
    except NotImplementedError:   # thetahat 0.1: θ* given separately
        fast = compile_observer(obs, dt=dt, theta_star=lugre.theta_star_expr())  # 0.1 API
    fast.run(tr.t[:50], tr.u[:50], tr.y[:50], state0=s0)
    out["compiled"] = 1e6 * best(lambda: fast.run(tr.t, tr.u, tr.y, state0=s0), 5) / N
print("RESULT " + json.dumps(out))
"""


def measure(src: Path | None, t_end: float) -> dict[str, float]:
    """One fresh process measuring every path with the thetahat of ``src`` (None: installed)."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    proc = subprocess.run([sys.executable, "-c", _MEASURE, str(t_end), str(BATCH_SIZE)],
                          env=env, capture_output=True, text=True, check=False)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"measurement failed ({src}):\n{proc.stderr[-3000:]}")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=2.0, help="record length (s) at 1 kHz")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--against", type=Path, default=None,
                    help="another thetahat src/ directory to measure in the same run")
    args = ap.parse_args(argv)
    here = Path(__file__).resolve().parents[1] / "src"
    trees = {"ours": here} | ({"other": args.against.resolve()} if args.against else {})
    rounds: dict[str, dict[str, list[float]]] = {name: {} for name in trees}
    wall0 = time.perf_counter()
    for rnd in range(args.rounds):
        for name, src in trees.items():
            res = measure(src, args.t_end)
            for k, v in res.items():
                rounds[name].setdefault(k, []).append(v)
            print(f"round {rnd}: {name:5} " + ", ".join(f"{k} {v:.3g} µs" for k, v in res.items()),
                  flush=True)
    out: dict = {}
    for stat, fn in (("median", statistics.median), ("best", min)):
        summary = {name: {k: fn(v) for k, v in res.items()} for name, res in rounds.items()}
        print(f"{stat} of {args.rounds} rounds (µs per step; {args.t_end:g} s at 1 kHz, "
              f"batch of {BATCH_SIZE}):")
        for name, res in summary.items():
            print(f"  {name:5} " + ", ".join(f"{k} {v:.3g}" for k, v in res.items()))
        if "other" in summary:
            ratios = {k: summary["ours"][k] / summary["other"][k] for k in summary["ours"]
                      if k in summary["other"]}
            print("  ratio ours ÷ other: " + ", ".join(f"{k} {v:.3f}" for k, v in ratios.items()))
            summary["ratio"] = ratios
        out[stat] = summary
    print(f"(wall {time.perf_counter() - wall0:.0f} s)")
    return out


if __name__ == "__main__":
    main()
