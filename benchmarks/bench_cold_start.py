"""Cold start: ``import thetahat``, and a model's first compiled run with an empty kernel cache.

Run:  .venv/bin/python benchmarks/bench_cold_start.py [--skip-guarded]

Every figure comes from fresh Python processes (nothing is imported or compiled beforehand):

* ``import thetahat`` (best of five processes), against ``import numpy, scipy, sympy`` — the
  dependencies any use of thetahat loads — measured the same way;
* the paper's observer of examples/lugre.toml through ``run_estimator(..., compiled=True)``
  on a 2 s record: two processes share a new, empty ``THETAHAT_CACHE_DIR``; the first
  compiles the model's kernel and writes it, the second loads it (see
  ``thetahat.estimation.kernel_cache``); each is timed from the call to the result, and
  against the same call on the Python path;
* the same for ``lugre.estimator("guarded").run`` (stage 1 and stage 2 kernels) unless
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

PAPER = """
import json, sys, time
from thetahat.modelfile import load_model, run_estimator
from thetahat.models import lugre
spec = load_model(sys.argv[1])
data = lugre.simulate(seed=0, t_end=2.0)
out = {}
for compiled in (True, False):
    t0 = time.perf_counter()
    res = run_estimator(spec, data.t, data.u, data.y, compiled=compiled)
    out["compiled" if compiled else "python"] = time.perf_counter() - t0
out["theta_end"] = float(res.theta_hat[-1, 0])
print(json.dumps(out))
"""

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


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-guarded", action="store_true")
    args = ap.parse_args(argv)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    out: dict[str, float] = {}
    out["import_thetahat_s"] = import_time("thetahat", env)
    out["import_deps_s"] = import_time("numpy, scipy, sympy", env)
    print(f"import thetahat: {out['import_thetahat_s'] * 1e3:.0f} ms (numpy, scipy, sympy: "
          f"{out['import_deps_s'] * 1e3:.0f} ms; ratio "
          f"{out['import_thetahat_s'] / out['import_deps_s']:.2f})")
    with tempfile.TemporaryDirectory() as cache:
        env_c = {**env, "THETAHAT_CACHE_DIR": cache}
        cold, warm = (child(PAPER, env_c, MODEL) for _ in range(2))
    assert cold["theta_end"] == warm["theta_end"], (cold, warm)
    out.update(paper_cold_s=cold["compiled"], paper_warm_s=warm["compiled"],
               paper_python_s=warm["python"])
    print(f"paper observer, examples/lugre.toml, 2 s record, compiled: empty cache "
          f"{cold['compiled']:.1f} s (the model's first compilation), warm cache "
          f"{warm['compiled']:.2f} s (ratio {cold['compiled'] / warm['compiled']:.0f}×); "
          f"Python path {warm['python']:.2f} s")
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
