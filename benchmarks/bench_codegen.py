"""Per-step cost of the generated C observer against the numba kernel and the Python step.

Run:  .venv/bin/python benchmarks/bench_codegen.py [--t-end 20] [--json out/bench_codegen.json]
      [--against OTHER/src]

One process, one record: the paper's DC motor (``lugre.observer()``, ε = 1, second observer,
1 kHz, ``lugre.simulate(seed=0)``), the same observer object for every back end:

* ``c_double`` / ``c_float``: ``generate_c`` output compiled with ``cc -O2`` (the flags of
  the acceptance) and called once through ctypes for the whole record; ``steps`` loops
  ``lugre_step`` only, ``record`` also stores the state and φ̂ per sample (what ``run`` does);
* ``numba``: ``compile_observer(...).run`` (the kernel's loop, which records state and φ̂);
* ``python``: ``ModifiedHighGainObserver.step`` per call (on the first 2000 samples);
* ``other_double_steps`` (with ``--against OTHER/src``): the C that another source tree's
  ``generate_c`` writes for the same observer (built in a subprocess with that tree first on
  the path, loaded here), timed in the same rounds, e.g. the hand-written C before the C was
  derived from the formulas.

Each time is the least CPU time (``time.process_time``: the 2-core machine is shared, and wall
time would count other processes) of REPEATS runs, taken round-robin over the back ends, in ns
per step. Printed: the table, the ratio C double ÷
numba (the issue asks for ≤ 1), and the float C error against double C. Where
``arm-none-eabi-gcc`` is installed, the code size of ``lugre.o`` for a Cortex-M4F
(``-mcpu=cortex-m4 -mfloat-abi=hard -mfpu=fpv4-sp-d16 -mthumb -Os``) in both precisions.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from thetahat.codegen import generate_c
from thetahat.modelfile import generate_c_from_model
from thetahat.codegen.loader import find_compiler, load_c
from thetahat.models import lugre

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "examples" / "lugre.toml"
REPEATS = 9
PYTHON_STEPS = 2000
ARM_FLAGS = ("-mcpu=cortex-m4", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-mthumb", "-Os",
             "-std=c99", "-ffunction-sections", "-fdata-sections")


def best(fn, repeats: int = REPEATS) -> float:
    """Least CPU time (process_time) of ``repeats`` calls: on a shared machine the wall clock
    also counts the time other processes hold the core."""
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def c_timers(code, tmp: Path, U: np.ndarray, Y: np.ndarray) -> tuple[dict, object]:
    """Callables timing the C steps alone and the record loop; the record run's result."""
    obs = load_c(code, tmp / code.name)
    Uc, Yc = (np.ascontiguousarray(a, dtype=obs.dtype) for a in (U, Y))

    def steps() -> None:
        s = obs.init()
        assert obs.run_steps(Uc, Yc, s) == 0

    def record() -> None:
        assert obs.run(U, Y).status == 0

    return {"steps": steps, "record": record}, obs.run(U, Y)


_OTHER = """
import sys
from thetahat.codegen import generate_c
from thetahat.codegen.loader import build
from thetahat.models import lugre
code = generate_c(lugre.observer(), dt=1e-3, name="other", theta_hat0=[float(sys.argv[2])])
print(build(code, sys.argv[1]))
"""


def other_timer(src: Path, tmp: Path, U: np.ndarray, Y: np.ndarray, theta_hat0: float):
    """Time ``other_run_steps`` of the C another tree generates (see the module docstring)."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    lib = subprocess.run([sys.executable, "-c", _OTHER, str(tmp / "other"), repr(theta_hat0)],
                         env=env, check=True, capture_output=True, text=True).stdout.strip()
    dll = ctypes.CDLL(lib)
    ptr = ctypes.POINTER(ctypes.c_double)
    Uc, Yc = (np.ascontiguousarray(a, dtype=np.float64) for a in (U, Y))
    state = np.zeros(64)                      # larger than either state struct

    def steps() -> None:
        assert dll.other_init(state.ctypes.data_as(ptr), None, None) == 0
        assert dll.other_run_steps(state.ctypes.data_as(ptr), ctypes.c_long(Y.shape[0]),
                                   Uc.ctypes.data_as(ptr), Yc.ctypes.data_as(ptr)) == 0

    return steps


def interleaved(timers: dict[str, object], repeats: int) -> dict[str, float]:
    """Best time of each callable, measured round-robin so that load changes hit all alike."""
    out = {name: math.inf for name in timers}
    for _ in range(repeats):
        for name, fn in timers.items():
            out[name] = min(out[name], best(fn, 1))
    return out


def arm_sizes(tmp: Path) -> dict[str, dict[str, int]] | None:
    gcc, size = shutil.which("arm-none-eabi-gcc"), shutil.which("arm-none-eabi-size")
    if gcc is None or size is None:
        return None
    out = {}
    for real in ("float", "double"):
        code = generate_c_from_model(MODEL, dt=1e-3, real=real, name=f"lugre_{real}")
        d = tmp / f"arm_{real}"
        code.write(d)
        subprocess.run([gcc, *ARM_FLAGS, "-Wall", "-Wextra", "-Werror", "-pedantic", "-c",
                        f"{code.name}.c", "-o", f"{code.name}.o"], cwd=d, check=True)
        text = subprocess.run([size, "-B", f"{code.name}.o"], cwd=d, check=True,
                              capture_output=True, text=True).stdout.splitlines()[1].split()
        out[real] = {"text": int(text[0]), "data": int(text[1]), "bss": int(text[2]),
                     "state_bytes": code.state_bytes, "const_bytes": code.const_bytes}
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=20.0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--against", type=Path, default=None,
                    help="another tree's src/: time the C its generate_c writes")
    args = ap.parse_args(argv)
    if find_compiler() is None:
        raise SystemExit("no C compiler (cc or $CC): nothing to benchmark")
    data = lugre.simulate(seed=0, t_end=args.t_end)
    U, Y = data.u, data.y
    N = Y.shape[0]
    obs = lugre.observer()
    theta_hat0 = [lugre.Scenario().theta_hat0]
    timers: dict[str, object] = {}
    results = {}
    with tempfile.TemporaryDirectory() as tmp_:
        tmp = Path(tmp_)
        for real in ("double", "float"):
            code = generate_c(obs, dt=1e-3, real=real, name=f"lugre_{real}",
                              theta_hat0=theta_hat0)
            fns, results[real] = c_timers(code, tmp, U, Y)
            timers[f"c_{real}_steps"], timers[f"c_{real}_record"] = fns["steps"], fns["record"]
        if args.against is not None:
            timers["other_double_steps"] = other_timer(args.against, tmp, U, Y, theta_hat0[0])
        arm = arm_sizes(tmp)
        ref = None
        try:
            from thetahat.estimation.observer.compiled import compile_observer
            fast = compile_observer(obs, dt=1e-3)
            state0 = obs.init(theta_hat0=theta_hat0)
            fast.run(data.t[:10], U[:10], Y[:10], state0=state0)       # JIT outside timing
            timers["numba_record"] = lambda: fast.run(data.t, U, Y, state0=state0)
            ref = fast.run(data.t, U, Y, state0=state0)
        except ImportError:
            pass
        rows = {name: t / N * 1e9 for name, t in interleaved(timers, REPEATS).items()}
    c = {real: {"result": res} for real, res in results.items()}
    s = obs.init(theta_hat0=theta_hat0)

    def python_steps() -> None:
        st = s
        for i in range(PYTHON_STEPS):
            st = obs.step(st, U[i], Y[i], 1e-3)

    rows["python_step"] = best(python_steps, 2) / PYTHON_STEPS * 1e9
    print(f"LuGre observer (lugre.observer()), {N} samples at 1 kHz; ns per step, best of "
          f"{REPEATS}:")
    for name, value in rows.items():
        print(f"  {name:<16} {value:12.1f}")
    ratios = {}
    if "numba_record" in rows:
        ratios = {"c_double_steps/numba_record": rows["c_double_steps"] / rows["numba_record"],
                  "c_double_record/numba_record": rows["c_double_record"] / rows["numba_record"],
                  "c_float_steps/numba_record": rows["c_float_steps"] / rows["numba_record"]}
        err = float(np.max(np.abs(c["double"]["result"].theta_hat - ref.theta_hat)))
        print(f"  |θ̂ C double − θ̂ numba| max = {err:.2e}")
    ratios["python_step/c_double_steps"] = rows["python_step"] / rows["c_double_steps"]
    if "other_double_steps" in rows:
        ratios["c_double_steps/other_double_steps"] = (rows["c_double_steps"]
                                                       / rows["other_double_steps"])
    for name, value in ratios.items():
        print(f"  ratio {name:<30} {value:10.3f}")
    f_err = float(np.max(np.abs(c["float"]["result"].theta_hat - c["double"]["result"].theta_hat)))
    print(f"  float C: max |θ̂_float − θ̂_double| = {f_err:.2e} N m (θ = 0.28)")
    if arm is None:
        print("  Cortex-M4F size: skipped (arm-none-eabi-gcc not installed)")
    else:
        for real, sz in arm.items():
            print(f"  Cortex-M4F lugre.c ({real}, -Os): text {sz['text']} B, data {sz['data']} B,"
                  f" bss {sz['bss']} B; state struct {sz['state_bytes']} B")
    payload = {"ns_per_step": rows, "ratios": ratios, "float_theta_abs_err": f_err,
               "cortex_m4f": arm}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(payload, indent=2))
    return payload


if __name__ == "__main__":
    main()
