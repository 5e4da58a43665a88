"""Per-sample cost of the generated guarded C against the generated C of its two stages.

Run:  .venv/bin/python benchmarks/bench_guarded_codegen.py [--t-end 5]

One process, one record: the paper's DC motor (``lugre.simulate(seed=0)``, 1 kHz), zoh, σ = 0.02,
one RK4 sub-step a sample. Three generated C estimators, each compiled with the harness's flags
(``cc -O2``) into a shared library with a loop over the record (``<name>_init``, then
``<name>_step`` per sample, storing θ̂), called once through ctypes:

* ``guarded``: :func:`~thetahat.codegen.guarded_c.generate_guarded_c` (stage 1, stage 2, the
  guard; no fits);
* ``ekf``: :func:`~thetahat.codegen.ekf_c.generate_ekf_c`, stage 2 alone;
* ``paper``: :func:`~thetahat.codegen.generate.generate_c`, stage 1 alone.

With ``arm-none-eabi-gcc`` installed it also prints, for a Cortex-M4F (``-mcpu=cortex-m4
-mfloat-abi=hard -mfpu=fpv4-sp-d16 -mthumb -Os``, double precision), each estimator linked
into a minimal program (init, then step in a loop; newlib, ``--gc-sections``): flash (text +
data) and the state struct's bytes.

Each time is the least CPU time (``time.process_time``; the machine is shared) of REPEATS runs
taken round-robin, in ns per sample. Printed, not asserted: the table and the ratios guarded ÷
(ekf + paper) — the guard's own overhead — and guarded ÷ ekf (issue 33 compares the guarded
step with an EKF step of the same model).
"""

from __future__ import annotations

import argparse
import ctypes
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from thetahat.codegen.ekf_c import generate_ekf_c
from thetahat.codegen.generate import generate_c
from thetahat.codegen.guarded_c import generate_guarded_c
from thetahat.codegen.harness import C_FLAGS
from thetahat.codegen.loader import find_compiler
from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.estimation.statistical.guarded import GuardedEstimator
from thetahat.models import lugre

REPEATS = 7
LOOP = """#include "{name}.h"
int {name}_loop(const double *U, const double *Y, long N, double *TH)
{{
    {name}_state st;
    long k;
    int status;
    {init}
    for (k = 0; k < N; ++k) {{
        status = {name}_step(&st, U + k, Y + k);
        if (status != 0) return status;
        TH[k] = {theta};
    }}
    return 0;
}}
"""


def best(fn) -> float:
    times = []
    for _ in range(REPEATS):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def library(code, sources: list[str], init: str, theta: str):
    out = Path(tempfile.mkdtemp())
    code.write(out)
    (out / "loop.c").write_text(LOOP.format(name=code.name, init=init, theta=theta))
    subprocess.run([find_compiler(), *C_FLAGS, "-fPIC", "-shared", "-o", "lib.so", *sources,
                    "loop.c", "-lm"], cwd=out, check=True)
    lib = ctypes.CDLL(str(out / "lib.so"))
    fn = getattr(lib, f"{code.name}_loop")
    dp = ctypes.POINTER(ctypes.c_double)
    fn.argtypes = [dp, dp, ctypes.c_long, dp]
    return fn


ARM_FLAGS = ("-mcpu=cortex-m4", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-mthumb", "-Os",
             "-std=c99", "-ffunction-sections", "-fdata-sections")
ARM_MAIN = """#include "{name}.h"
static {name}_state st;
volatile double u_in[1], y_in[1], out;
int main(void)
{{
    double u[1], y[1];
    {init}
    for (;;) {{
        u[0] = u_in[0];
        y[0] = y_in[0];
        (void){name}_step(&st, u, y);
        out = {theta};
    }}
}}
"""


def arm_size(code, sources: list[str], init: str, theta: str) -> dict[str, int] | None:
    """Flash and state bytes of ``code`` linked for a Cortex-M4F, or None without the tools."""
    cc, nm, size = (shutil.which(f"arm-none-eabi-{t}") for t in ("gcc", "nm", "size"))
    if cc is None or nm is None or size is None:
        return None
    out = Path(tempfile.mkdtemp())
    code.write(out)
    (out / "m4.c").write_text(ARM_MAIN.format(name=code.name, init=init, theta=theta))
    subprocess.run([cc, *ARM_FLAGS, "-Wl,--gc-sections", "--specs=nosys.specs", "-o", "m4.elf",
                    "m4.c", *sources, "-lm"], cwd=out, check=True, capture_output=True)
    text, data, _bss = (int(v) for v in subprocess.run(
        [size, "m4.elf"], cwd=out, check=True, capture_output=True,
        text=True).stdout.splitlines()[1].split()[:3])
    sym = subprocess.run([nm, "-S", "m4.elf"], cwd=out, check=True, capture_output=True,
                         text=True).stdout
    state = next(int(line.split()[1], 16) for line in sym.splitlines()
                 if line.endswith(" st"))
    return {"flash": text + data, "state": state}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--t-end", type=float, default=5.0, help="record length in s")
    args = parser.parse_args()
    if find_compiler() is None:
        print("needs a C compiler; skipped")
        return 0
    data = lugre.simulate(seed=0, t_end=args.t_end)
    t = np.asarray(data.t, dtype=np.float64)
    U = np.ascontiguousarray(np.reshape(data.u, (t.size, -1)), dtype=np.float64)
    Y = np.ascontiguousarray(np.reshape(data.y, (t.size, -1)), dtype=np.float64)
    N, dt = t.size, float(t[1] - t[0])
    system = lugre.system()
    obs = lugre.observer().with_run_options(hold="zoh")
    est = GuardedEstimator(stage1=obs, noise_std=0.02, hold="zoh", use_fits=False,
                           substeps=1, compiled=False)
    ekf = JointEKF(system=system, noise_std=0.02, hold="zoh", substeps=1, compiled=False)
    g = generate_guarded_c(est, dt=dt, name="bg")
    e = generate_ekf_c(ekf, dt=dt, name="be")
    o = generate_c(obs, dt=dt, name="bo")
    n = system.n
    runs = {
        "guarded": library(g, ["bg.c", "bg_stage1.c"], "if (bg_init(&st) != 0) return -1;",
                           "st.theta_hat[0]"),
        "ekf": library(e, ["be.c"], "be_init(&st);", f"st.s[{n}]"),
        "paper": library(o, ["bo.c"], "if (bo_init(&st, 0, 0) != 0) return -1;",
                         "bo_theta_hat(&st)[0]"),
    }
    dp = ctypes.POINTER(ctypes.c_double)
    TH = {k: np.empty(N) for k in runs}

    def call(key: str) -> None:
        rc = runs[key](U.ctypes.data_as(dp), Y.ctypes.data_as(dp), N,
                       TH[key].ctypes.data_as(dp))
        if rc != 0:
            raise RuntimeError(f"the {key} C stopped with status {rc}")

    # the peer: the joint EKF of the same model written by hand (bench_ekf_codegen.py), with
    # its RK4 map and with one Euler step a sample, timed in the same rounds
    from bench_ekf_codegen import hand_written
    hand_rk4, _, hand_euler, _ = hand_written(Path(tempfile.mkdtemp()), t, U, Y)
    peers_c = {"hand-written RK4": hand_rk4, "hand-written Euler": hand_euler}
    for key in runs:
        call(key)
    for run in peers_c.values():
        run()
    times: dict[str, list[float]] = {k: [] for k in [*runs, *peers_c]}
    for _ in range(REPEATS):
        for key in runs:
            times[key].append(best(lambda: call(key)) / N * 1e9)
        for key, run in peers_c.items():
            times[key].append(best(run) / N * 1e9)
    ns = {k: min(v) for k, v in times.items()}
    print(f"LuGre (n={n}, p={system.p}), {N} samples at 1 kHz, zoh, least CPU time of "
          f"{REPEATS}x{REPEATS} runs")
    for key in runs:
        print(f"  {key:8s} C step {ns[key]:9.1f} ns/sample")
    print(f"  guarded / (ekf + paper) {ns['guarded'] / (ns['ekf'] + ns['paper']):7.3f}"
          "   (the guard's own cost)")
    print(f"  guarded / ekf           {ns['guarded'] / ns['ekf']:7.3f}")
    for key in peers_c:
        print(f"  {key} EKF C step {ns[key]:9.1f} ns/sample: guarded / it "
              f"{ns['guarded'] / ns[key]:6.3f} (issue 33: ≤ 3), ekf / it "
              f"{ns['ekf'] / ns[key]:6.3f} (≤ 1.5)")
    sizes = {"guarded": arm_size(g, ["bg.c", "bg_stage1.c"], "(void)bg_init(&st);",
                                 "st.theta_hat[0]"),
             "ekf": arm_size(e, ["be.c"], "be_init(&st);", f"st.s[{n}]"),
             "paper": arm_size(o, ["bo.c"], "(void)bo_init(&st, 0, 0);",
                               "bo_theta_hat(&st)[0]")}
    if sizes["guarded"] is None:
        print("  Cortex-M4F: skipped (arm-none-eabi-gcc not installed)")
    else:
        for key, sz in sizes.items():
            assert sz is not None
            print(f"  Cortex-M4F {key:8s} (double, -Os, linked with newlib): flash "
                  f"{sz['flash']} B, state {sz['state']} B")
    lo, hi = system.parameter_set.lower, system.parameter_set.upper
    inside = bool(np.all((TH["guarded"] >= lo[0]) & (TH["guarded"] <= hi[0])))
    print(f"  guarded θ̂ in Θ at every sample: {inside}; final θ̂ guarded "
          f"{TH['guarded'][-1]:.4f}, ekf {TH['ekf'][-1]:.4f}, paper {TH['paper'][-1]:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
