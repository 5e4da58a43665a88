"""How each method's cost grows with the record: seconds per sample, log-log slope, memory.

Run:  .venv/bin/python benchmarks/bench_scaling.py [--quick] [--models lugre prop3]
      [--methods paper guarded mle ekf trust] [--max-seconds 300] [--traced]
      [--json out.json]

For each model (default: examples/lugre.toml and examples/prop3.toml) a record of 10⁴, 10⁵
and 10⁶ samples (``--quick``: 10⁴ and 10⁵) is made from the model's ``[scenario]``, simulated
once and repeated end to end at its sampling rate (so the record is as hard as the scenario
throughout), and written as CSV. Measured in this run:

* **parse** — ``numpy.loadtxt(..., delimiter=",")`` of that CSV (NumPy's fastest reader of
  it; best of three up to 10⁵ samples), the floor any CSV job pays;
* each **method** — ``run_estimator(spec, t, u, y, method=M, diagnose=False)`` on the first N
  samples, with the compiled kernels (``compiled=True``; ``--python`` for the NumPy path), in
  one fresh process per method and model, after a warm-up run on 2 000 samples (imports,
  kernel cache); ``trust`` is the trust report (``diagnose``) of the paper's estimate, timed
  alone. ``ekf`` (the joint EKF) is the reference pass.

Printed per model and N: seconds, µs per sample, the ratios to the parse and to the EKF's pass
at the same N, and the peak memory the run added (the process's ``ru_maxrss`` after the run
less its resident size before it) against the input arrays' size (t, u, y as float64); then
each method's log-log slope of seconds against N (1: linear). ``--traced`` measures the
memory instead as the peak of the run's traced allocations (``tracemalloc``: NumPy's arrays
and Python's objects, the result's included; not the interpreter, the libraries or numba's
compiled code, which ``ru_maxrss`` counts once per process and which make its figure at 10⁴
samples about that at 10⁶); tracing slows the Python parts, so its times are not the
method's. A run that takes longer than
``--max-seconds`` is stopped, and a larger N whose predicted time (the last time scaled by N
to the power max(slope, 1)) exceeds it is not started: both print "skipped: > S s".

Nothing is asserted; the figures are this machine's, from one run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent / "examples"
SIZES = (10_000, 100_000, 1_000_000)
QUICK_SIZES = (10_000, 100_000)
METHODS = ("paper", "guarded", "mle", "ekf", "trust")
#: Samples of the warm-up run in each method's process (imports, kernel cache, first calls).
WARMUP = 2_000

CHILD = r"""
import json, resource, sys, time, warnings
import numpy as np
from thetahat.modelfile import load_model, run_estimator

warnings.simplefilter("ignore")          # the figures, not the estimates, are wanted here
model, npz, method, sizes, compiled, traced = json.loads(sys.argv[1])
spec = load_model(model)
data = np.load(npz)
t, u, y = data["t"], data["u"], data["y"]


def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def once(n):
    if method != "trust":
        start = time.perf_counter()
        run_estimator(spec, t[:n], u[:n], y[:n], method=method, compiled=compiled,
                      diagnose=False)
        return time.perf_counter() - start
    from thetahat.estimation.statistical.trust import trust_report
    from thetahat.modelfile import start_x_hat
    res = run_estimator(spec, t[:n], u[:n], y[:n], method="paper", compiled=compiled,
                        diagnose=False)
    start = time.perf_counter()
    trust_report(spec.system, res.t, np.ascontiguousarray(u[:n]), np.ascontiguousarray(y[:n]),
                 res.theta_hat[-1], spec.parameter_names, x_hat0=start_x_hat(spec, y[:n]),
                 compiled=compiled)
    return time.perf_counter() - start


once(min(sizes[0], WARMUP))
for n in sizes:
    print(json.dumps({"event": "start", "n": n}), flush=True)
    before = rss()
    if traced:
        import tracemalloc
        tracemalloc.start()
        seconds = once(n)
        added = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    else:
        seconds = once(n)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024     # Linux: KiB
        added = max(peak - before, 0)
    print(json.dumps({"event": "done", "n": n, "s": seconds, "added": added}), flush=True)
""".replace("WARMUP", str(WARMUP))


def make_record(model: Path, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, u, y) of ``n`` samples: the model's scenario simulated once, repeated."""
    from thetahat.modelfile import load_model
    from thetahat.modelfile.study import simulate_model
    spec = load_model(model)
    run = simulate_model(spec, seed=0)
    reps = -(-n // run.t.size)
    t = np.arange(n) / spec.scenario.fs
    return t, np.tile(run.u, (reps, 1))[:n], np.tile(run.y, (reps, 1))[:n]


def parse_seconds(t: np.ndarray, u: np.ndarray, y: np.ndarray, folder: Path) -> float:
    """numpy.loadtxt of the record written as CSV (17 significant digits)."""
    from thetahat.io.datafile import write_csv_table
    cols = {"t": t} | {f"u{i + 1}": u[:, i] for i in range(u.shape[1])} \
        | {f"y{i + 1}": y[:, i] for i in range(y.shape[1])}
    path = folder / f"record_{t.size}.csv"
    write_csv_table(path, cols)
    best = math.inf
    for _ in range(3 if t.size <= 100_000 else 1):         # best of three when it is cheap
        start = time.perf_counter()
        np.loadtxt(path, delimiter=",", skiprows=1)
        best = min(best, time.perf_counter() - start)
    path.unlink()
    return best


def _predicted(times: dict[int, float], n: int) -> float | None:
    """The time at n from the measured ones: scaled by N^max(slope, 1)."""
    if not times:
        return None
    ns = sorted(times)
    slope = max(_slope({k: times[k] for k in ns}) or 1.0, 1.0)
    return times[ns[-1]] * (n / ns[-1]) ** slope


def _slope(times: dict[int, float]) -> float | None:
    ns = sorted(times)
    if len(ns) < 2:
        return None
    return float(np.polyfit(np.log(ns), np.log([times[k] for k in ns]), 1)[0])


def run_method(model: Path, npz: Path, method: str, sizes: tuple[int, ...], compiled: bool,
               max_seconds: float, traced: bool = False) -> dict[int, dict]:
    """One process for a method on one model: ``{n: {"s", "added"} or {"skipped": why}}``."""
    out: dict[int, dict] = {}
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([sys.executable, "-c", CHILD,
                                 json.dumps([str(model), str(npz), method, list(sizes),
                                             compiled, traced])],
                                stdout=subprocess.PIPE, stderr=err, bufsize=0, env=env)
        try:
            _follow(proc, out, max_seconds)
        finally:
            if proc.poll() is None:
                proc.kill()                       # this run's own child, by its handle
            proc.wait()
        if proc.returncode not in (0, -9) and not any("s" in v for v in out.values()):
            err.seek(0)
            lines = err.read().strip().splitlines()
            out[sizes[0]] = {"skipped": "failed: " + (lines[-1] if lines
                                                      else f"exit {proc.returncode}")}
    why = next((v["skipped"] for v in out.values() if "skipped" in v), None)
    out.pop(0, None)
    return {n: out.get(n, {"skipped": why or "not run"}) for n in sizes}


def _follow(proc: subprocess.Popen, out: dict[int, dict], max_seconds: float) -> None:
    """Read the child's events into ``out`` until it ends, a run (or the warm-up) outlasts
    ``max_seconds``, or the next N is predicted to."""
    assert proc.stdout is not None
    fd, pending = proc.stdout.fileno(), b""
    current, started = None, time.monotonic()          # the warm-up runs first
    while True:
        if time.monotonic() - started > max_seconds:
            if current is not None:
                out[current] = {"skipped": f"> {max_seconds:g} s"}
            else:
                out[0] = {"skipped": f"> {max_seconds:g} s (warm-up)"}
            return
        if b"\n" not in pending:
            ready, _, _ = select.select([fd], [], [], 0.5)
            if not ready:
                if proc.poll() is not None:
                    return
                continue
            chunk = os.read(fd, 65536)
            if not chunk:
                return
            pending += chunk
            continue
        line, pending = pending.split(b"\n", 1)
        event = json.loads(line)
        if event["event"] == "start":
            guess = _predicted({k: v["s"] for k, v in out.items() if "s" in v}, event["n"])
            if guess is not None and guess > max_seconds:
                out[event["n"]] = {"skipped": f"> {max_seconds:g} s (predicted {guess:.0f} s)"}
                return
            current, started = event["n"], time.monotonic()
        else:
            out[event["n"]] = {"s": event["s"], "added": event["added"]}
            current, started = None, time.monotonic()


def report(model: str, sizes: tuple[int, ...], parse: dict[int, float],
           results: dict[str, dict[int, dict]], input_bytes: dict[int, int],
           traced: bool = False) -> None:
    ekf = {n: v["s"] for n, v in results.get("ekf", {}).items() if "s" in v}
    print(f"\n{model}: parse = numpy.loadtxt of the CSV; ×ekf = the joint EKF at the same N"
          + ("; MB = the run's traced peak (tracemalloc; times slowed by tracing)" if traced
             else "; +MB = ru_maxrss added by the run"))
    print(f"{'method':<8} {'N':>9} {'s':>9} {'µs/sample':>10} {'×parse':>8} {'×ekf':>7} "
          f"{'MB' if traced else '+MB':>8} {'×input':>7}")
    for n in sizes:
        print(f"{'parse':<8} {n:>9,} {parse[n]:>9.3f} {1e6 * parse[n] / n:>10.2f}")
    for method, rows in results.items():
        for n in sizes:
            row = rows.get(n, {"skipped": "not run"})
            if "s" not in row:
                why = row["skipped"]
                print(f"{method:<8} {n:>9,}  " + (f"skipped: {why}" if why.startswith(">")
                                                  else why))
                continue
            s = row["s"]
            vs_ekf = f"{s / ekf[n]:>7.1f}" if n in ekf else f"{'–':>7}"
            print(f"{method:<8} {n:>9,} {s:>9.3f} {1e6 * s / n:>10.2f} {s / parse[n]:>8.2f} "
                  f"{vs_ekf} {row['added'] / 2**20:>8.1f} {row['added'] / input_bytes[n]:>7.1f}")
    slopes = {m: _slope({n: v["s"] for n, v in rows.items() if "s" in v})
              for m, rows in results.items()}
    slopes["parse"] = _slope(parse)
    print("log-log slope of seconds against N: " + ", ".join(
        f"{m} {s:.2f}" if s is not None else f"{m} –" for m, s in slopes.items()))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10⁴ and 10⁵ samples only")
    ap.add_argument("--sizes", type=int, nargs="+", default=None, help="record lengths")
    ap.add_argument("--models", nargs="+", default=["lugre", "prop3"],
                    help="shipped model files (examples/NAME.toml)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--max-seconds", type=float, default=300.0,
                    help="longest run of a method at one N (default: 300)")
    ap.add_argument("--python", action="store_true", help="the NumPy path (compiled=False)")
    ap.add_argument("--traced", action="store_true",
                    help="memory as the run's traced peak (tracemalloc), not ru_maxrss")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    sizes = tuple(sorted(args.sizes or (QUICK_SIZES if args.quick else SIZES)))
    payload: dict = {}
    print(f"bench_scaling: N = {', '.join(f'{n:,}' for n in sizes)}; "
          f"{'NumPy path' if args.python else 'compiled kernels'}; a method stops at "
          f"{args.max_seconds:g} s per run")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in args.models:
            model = EXAMPLES / f"{name}.toml"
            t, u, y = make_record(model, sizes[-1])
            npz = folder / f"{name}.npz"
            np.savez(npz, t=t, u=u, y=y)
            parse = {n: parse_seconds(t[:n], u[:n], y[:n], folder) for n in sizes}
            input_bytes = {n: 8 * n * (1 + u.shape[1] + y.shape[1]) for n in sizes}
            results = {}
            for method in args.methods:
                start = time.perf_counter()
                results[method] = run_method(model, npz, method, sizes, not args.python,
                                             args.max_seconds, args.traced)
                print(f"  {name} {method}: {time.perf_counter() - start:.0f} s", flush=True)
            report(name, sizes, parse, results, input_bytes, args.traced)
            payload[name] = {"parse_s": parse, "input_bytes": input_bytes,
                             "methods": results}
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(payload, indent=2, default=str))
    return payload


if __name__ == "__main__":
    main()
