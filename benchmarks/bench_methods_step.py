"""Per-step cost of every method (paper, guarded, mle, JointEKF) on each back end, one run.

Run:  OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_methods_step.py
      [--t-end 2] [--t-end-python 0.3]

The paper's DC motor (``thetahat.models.lugre``, 1 kHz, its default estimators). Back ends:

* ``python``: ``compiled=False`` (NumPy/Python loops), on a ``--t-end-python`` record;
* ``numba``: ``compiled=True`` with ``THETAHAT_C=0`` (every kernel numba's);
* ``C``: the default with a C compiler: the paper's observer, and the guarded estimator's
  stage 1, on the C printed from the formulas (``thetahat.codegen.native``); a run's guarded
  stage 2, MAP fits and EKF do not run in C (their generated C, ``codegen --method ekf`` /
  ``guarded``, is for controllers: ``bench_ekf_codegen.py``, ``bench_guarded_codegen.py``), so
  their row is empty.

Each figure is the CPU time of this process (``time.process_time``, best of ``--rounds``
after one warm-up run that compiles) divided by the record's samples: µs per sample of a
whole ``run`` (for guarded and mle, fits included). Printed: a Markdown table of µs and each
back end's ratio to numba's, measured in this one run; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import time

METHODS = ("paper", "guarded", "mle", "ekf")
BACK_ENDS = ("python", "numba", "C")


def estimator(method: str, back_end: str, dt: float):
    """The lugre estimator of ``method`` on ``back_end``, or None where it has none."""
    from thetahat.codegen.generate import supports_c
    from thetahat.codegen.native import NativeObserver, native_enabled
    from thetahat.estimation.observer.compiled import compile_observer
    from thetahat.models import lugre

    os.environ["THETAHAT_C"] = "0" if back_end == "numba" else "1"
    if back_end == "C" and (method in ("mle", "ekf") or not native_enabled()):
        return None
    if method != "paper":
        return lugre.estimator(method, compiled=back_end != "python")
    obs = lugre.observer()
    if back_end == "python":
        return obs
    if back_end == "numba":
        return compile_observer(obs, dt=dt)
    assert supports_c(obs)
    return NativeObserver(obs, lambda: compile_observer(obs, dt=dt))


def per_sample_us(est, data, rounds: int) -> float:
    best = float("inf")
    for i in range(rounds + 1):                  # the first run compiles: not timed
        t0 = time.process_time()
        est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
        if i:
            best = min(best, time.process_time() - t0)
    return best / data.t.size * 1e6


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=2.0, help="record (s) of compiled paths")
    ap.add_argument("--t-end-python", type=float, default=0.3, help="record (s) of Python")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args(argv)
    from thetahat.models import lugre
    long, short = (lugre.simulate(seed=0, t_end=t) for t in (args.t_end, args.t_end_python))
    dt = float(long.t[1] - long.t[0])
    out: dict[str, dict[str, float | None]] = {}
    saved = os.environ.get("THETAHAT_C")
    try:
        for method in METHODS:
            out[method] = {}
            for back_end in BACK_ENDS:
                est = estimator(method, back_end, dt)
                data = short if back_end == "python" else long
                out[method][back_end] = (None if est is None
                                         else per_sample_us(est, data, args.rounds))
    finally:
        if saved is None:
            os.environ.pop("THETAHAT_C", None)
        else:
            os.environ["THETAHAT_C"] = saved
    print(f"µs per sample of a whole run (CPU), LuGre at 1 kHz; compiled paths on "
          f"{args.t_end:g} s, Python on {args.t_end_python:g} s; ratio to numba in brackets\n")
    print("| method | " + " | ".join(BACK_ENDS) + " |")
    print("|---|" + "---|" * len(BACK_ENDS))
    for method, row in out.items():
        ref = row["numba"]
        cells = []
        for back_end in BACK_ENDS:
            v = row[back_end]
            cells.append("—" if v is None else
                         f"{v:.3g} µs ({v / ref:.3g}×)" if ref else f"{v:.3g} µs")
        print(f"| {method} | " + " | ".join(cells) + " |")
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
