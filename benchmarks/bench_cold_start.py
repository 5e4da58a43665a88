"""Cold start: ``import thetahat``, and a model's first run with an empty kernel cache.

Run:  .venv/bin/python benchmarks/bench_cold_start.py [--repeat 2] [--skip-numba]
      [--skip-guarded]

Every figure comes from fresh Python processes (nothing is imported or compiled beforehand):

* ``import thetahat`` (best of five processes), against ``import numpy, scipy, sympy`` — the
  dependencies any use of thetahat loads — measured the same way;
* ``thetahat estimate examples/lugre.toml`` on a 30 000-sample record (above
  ``COMPILE_MIN_SAMPLES``, so the observer runs compiled; the trust report's stage-2 kernels
  compile too) in a new process with a new, empty ``THETAHAT_CACHE_DIR``, then once more with
  that cache filled (warm): on the default back end (the C printed from the formulas, built by
  the system's compiler, when there is one) and with ``THETAHAT_C=0`` (numba); each cold
  figure the best of ``--repeat`` processes (each with its own empty cache); wall time and the
  CPU time of the process tree (the machine's load shows as their difference); ratios cold ÷
  warm and cold ÷ the 10 s target;
* ``lugre.estimator("guarded").run`` on a 2 s record, empty cache then warm, unless
  ``--skip-guarded``.

Printed: the times and their ratios (one run); nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

IMPORTS = """
import json, time
t0 = time.perf_counter()
import {modules}
print(json.dumps({{"s": time.perf_counter() - t0}}))
"""

CLI = """
import json, resource, subprocess, sys, time
t0 = time.perf_counter()
subprocess.run([sys.executable, "-m", "thetahat", "estimate", *sys.argv[1:], "--no-progress"],
               check=True, capture_output=True)
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": ru.ru_utime + ru.ru_stime}))
"""

#: The issue's target for a model's first run (s).
TARGET_S = 10.0
#: Samples of the record: above COMPILE_MIN_SAMPLES (20 000), so the observer runs compiled.
SAMPLES = 30_000

GUARDED = """
import json, time
from thetahat.models import lugre
est = lugre.estimator("guarded")
data = lugre.simulate(seed=0, t_end=2.0)
t0 = time.perf_counter()
res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
print(json.dumps({"first_run_s": time.perf_counter() - t0,
                  "theta_end": float(res.theta_hat[-1, 0])}))
"""

MODEL = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "examples", "lugre.toml")


def child(code: str, env: dict[str, str], *args: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", code, *args], env=env, check=True,
                          capture_output=True, text=True)
    return json.loads(proc.stdout.splitlines()[-1])


def import_time(modules: str, env: dict[str, str], repeats: int = 5) -> float:
    return min(child(IMPORTS.format(modules=modules), env)["s"] for _ in range(repeats))


def lugre_record(path: str) -> None:
    """SAMPLES samples of the LuGre scenario (repeated end to end) as a CSV t,u,y."""
    import numpy as np

    from thetahat.models import lugre
    run = lugre.simulate(seed=0)
    reps = -(-SAMPLES // run.t.size)
    dt = float(run.t[1] - run.t[0])
    u = np.tile(run.u.reshape(-1), reps)[:SAMPLES]
    y = np.tile(run.y.reshape(-1), reps)[:SAMPLES]
    np.savetxt(path, np.c_[np.arange(SAMPLES) * dt, u, y], delimiter=",", header="t,u,y",
               comments="", fmt="%.17g")


def cli_cold_warm(env: dict[str, str], data: str, out: str, repeat: int
                  ) -> tuple[dict, dict]:
    """Best of ``repeat`` cold runs (each with its own empty cache) and a warm one."""
    colds = []
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as cache:
            env_c = {**env, "THETAHAT_CACHE_DIR": cache}
            colds.append(child(CLI, env_c, MODEL, data, "-o", out))
            warm = child(CLI, env_c, MODEL, data, "-o", out)
    return min(colds, key=lambda r: r["wall_s"]), warm


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="cold runs per back end (best kept)")
    ap.add_argument("--skip-numba", action="store_true", help="no THETAHAT_C=0 runs")
    ap.add_argument("--skip-guarded", action="store_true")
    args = ap.parse_args(argv)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    out: dict[str, float] = {}
    out["import_thetahat_s"] = import_time("thetahat", env)
    out["import_deps_s"] = import_time("numpy, scipy, sympy", env)
    print(f"import thetahat: {out['import_thetahat_s'] * 1e3:.0f} ms (numpy, scipy, sympy: "
          f"{out['import_deps_s'] * 1e3:.0f} ms; ratio "
          f"{out['import_thetahat_s'] / out['import_deps_s']:.2f})")
    backends = [("default", {})] + ([] if args.skip_numba else [("numba", {"THETAHAT_C": "0"})])
    with tempfile.TemporaryDirectory() as tmp:
        data, est = os.path.join(tmp, "log.csv"), os.path.join(tmp, "estimates.csv")
        lugre_record(data)
        for name, extra in backends:
            cold, warm = cli_cold_warm({**env, **extra}, data, est, args.repeat)
            out.update({f"estimate_{name}_cold_s": cold["wall_s"],
                        f"estimate_{name}_cold_cpu_s": cold["cpu_s"],
                        f"estimate_{name}_warm_s": warm["wall_s"]})
            print(f"thetahat estimate examples/lugre.toml, {SAMPLES} samples, {name} back end"
                  f"{' (THETAHAT_C=0)' if extra else ''}: empty cache {cold['wall_s']:.1f} s "
                  f"wall ({cold['cpu_s']:.1f} s CPU; best of {args.repeat}), warm "
                  f"{warm['wall_s']:.1f} s wall ({warm['cpu_s']:.1f} s CPU); cold ÷ warm "
                  f"{cold['wall_s'] / warm['wall_s']:.1f}, cold ÷ {TARGET_S:.0f} s target "
                  f"{cold['wall_s'] / TARGET_S:.2f} (CPU {cold['cpu_s'] / TARGET_S:.2f})")
    if not args.skip_guarded:
        with tempfile.TemporaryDirectory() as cache:
            env_c = {**env, "THETAHAT_CACHE_DIR": cache}
            g_cold, g_warm = (child(GUARDED, env_c) for _ in range(2))
        assert g_cold["theta_end"] == g_warm["theta_end"], (g_cold, g_warm)
        out.update(guarded_cold_s=g_cold["first_run_s"], guarded_warm_s=g_warm["first_run_s"])
        print(f"first guarded run of a fresh process (2 s record): empty cache "
              f"{g_cold['first_run_s']:.1f} s, warm cache {g_warm['first_run_s']:.2f} s "
              f"(ratio {g_cold['first_run_s'] / g_warm['first_run_s']:.0f}×)")
    return out


if __name__ == "__main__":
    main()
