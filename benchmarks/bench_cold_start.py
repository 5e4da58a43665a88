"""Time to the first guarded estimate in a fresh process: empty kernel cache vs warm cache.

Run:  .venv/bin/python benchmarks/bench_cold_start.py

Two fresh Python processes share a new, empty ``THETAHAT_CACHE_DIR``. The first compiles every
numba kernel (stage 1 and stage 2) and writes them; the second loads them (see
``thetahat.estimation.kernel_cache``). Each times ``lugre.estimator("guarded").run`` on a 2 s
record, first call included. Printed: both times and their ratio (one run).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

CHILD = """
import json, time
from thetahat.models import lugre
est = lugre.estimator("guarded")
data = lugre.simulate(seed=0, t_end=2.0)
t0 = time.perf_counter()
res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
print(json.dumps({"first_run_s": time.perf_counter() - t0,
                  "theta_end": float(res.theta_hat[-1, 0])}))
"""


def main() -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "THETAHAT_CACHE_DIR": cache, "OPENBLAS_NUM_THREADS": "1"}
        cold, warm = (json.loads(subprocess.run([sys.executable, "-c", CHILD], env=env,
                                                check=True, capture_output=True, text=True)
                                 .stdout.splitlines()[-1]) for _ in range(2))
    assert cold["theta_end"] == warm["theta_end"], (cold, warm)   # the same machine code
    print(f"first guarded run of a fresh process (2 s record): empty cache "
          f"{cold['first_run_s']:.1f} s, warm cache {warm['first_run_s']:.2f} s "
          f"(ratio {cold['first_run_s'] / warm['first_run_s']:.0f}×)")
    return {"cold_s": cold["first_run_s"], "warm_s": warm["first_run_s"]}


if __name__ == "__main__":
    main()
