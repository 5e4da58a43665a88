"""The MAP fit's sweep with the RK4 stage's variational equations compiled into the step, and
called.

Run:  .venv/bin/python benchmarks/bench_plant_kernel.py [--samples 20000] [--models ...]

Every estimator with fits (guarded, mle), the trust report and the bound spend their time in
one loop: the model propagated over a sample by RK4 sub-steps, with Φ = ∂x⁺/∂x and
Γ = ∂x⁺/∂θ from the variational equations of each stage (``plant_kernel.stage_jac``). The
printed plant module compiles ``stage_jac`` into ``propagate_into`` (numba's
``inline='always'``, ``plant_kernel.INLINED``) with the state's dimension a constant of the
module, so that the loops over x unroll. This benchmark measures what that buys, in one run:
for each model, the same sweep kernel (``sweep.sweep_kernel``, Gauss–Newton's A and b on the
whole record) printed over the two plant modules (``model_kernel(inline=True)`` and
``inline=False``), on the same record at the sub-steps ``choose_substeps`` picks there, the
least CPU time of REPEATS runs taken in turn. Printed: ns a sample of each, their ratio, and
the largest difference of J and A between the two (relative; the same arithmetic, so 0 up to
the order of operations LLVM picks).

Records: the Silverbox training split and the EMPS record (measured), and the scenarios of
``examples/lugre.toml``, ``two_inertia.toml`` and ``actuator.toml`` simulated once, each cut
to ``--samples``.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from thetahat.estimation.statistical.plant_kernel import (Propagation, choose_substeps,
                                                         model_kernel)
from thetahat.estimation.statistical.sweep import sweep_kernel
from thetahat.io.datafile import read_data
from thetahat.modelfile import load_model, start_x_hat
from thetahat.modelfile.study import simulate_model

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
MODELS = ("silverbox", "emps", "lugre", "two_inertia", "actuator")
MEASURED = {"silverbox": EXAMPLES / "data" / "silverbox" / "SNLS80mV.mat",
            "emps": EXAMPLES / "data" / "emps" / "DATA_EMPS.mat"}
REPEATS = 5


def record(name: str, samples: int):
    """(spec, t, U, Y) of a model file's record (its data when measured, else its scenario)."""
    spec = load_model(EXAMPLES / f"{name}.toml")
    if name in MEASURED:
        data = read_data(MEASURED[name], spec.layout)
        t, u, y = data.t, data.u, data.y
    else:
        run = simulate_model(spec, seed=0)
        t, u, y = run.t, run.u, run.y
    n = min(samples, t.shape[0])
    U = np.ascontiguousarray(np.asarray(u, dtype=np.float64).reshape(t.shape[0], -1)[:n])
    Y = np.ascontiguousarray(np.asarray(y, dtype=np.float64).reshape(t.shape[0], -1)[:n])
    return spec, np.ascontiguousarray(t[:n], dtype=np.float64), U, Y


def measure(name: str, samples: int) -> dict:
    spec, t, U, Y = record(name, samples)
    system = spec.system
    n, p = system.n, system.p
    theta = np.asarray(spec.estimator.theta_hat0, dtype=np.float64)
    x0 = np.asarray(start_x_hat(spec, Y), dtype=np.float64)
    sigma = np.maximum(np.std(Y, axis=0), 1e-12) * 1e-2
    hold = "bandlimited" if name == "silverbox" else "foh"    # as their docs pages run them
    kernels = {inline: model_kernel(system, compiled=True, inline=inline)
               for inline in (True, False)}
    sub = choose_substeps(kernels[True], t, U, Y, theta, x0, sigma, hold=hold)
    pc, WT = Propagation(hold=hold, substeps=sub).arrays()
    sweeps = {inline: sweep_kernel(k) for inline, k in kernels.items()}
    nq, N = n + p, t.shape[0]
    out = {}
    for inline, sw in sweeps.items():          # compile, and keep one result each
        A, b, T, X = np.empty((nq, nq)), np.empty(nq), np.empty((n, nq)), np.empty((N, n))
        J = sw(x0, theta, U, Y, t, 0, N, False, 1.0 / sigma ** 2, pc.copy(), WT.copy(), True,
               A, b, T, X)
        out[inline] = (J, A.copy())
    best = {True: np.inf, False: np.inf}
    for _ in range(REPEATS):
        for inline, sw in sweeps.items():
            A, b, T, X = np.empty((nq, nq)), np.empty(nq), np.empty((n, nq)), np.empty((N, n))
            start = time.process_time()
            sw(x0, theta, U, Y, t, 0, N, False, 1.0 / sigma ** 2, pc.copy(), WT.copy(), True,
               A, b, T, X)
            best[inline] = min(best[inline], time.process_time() - start)
    (J1, A1), (J0, A0) = out[True], out[False]
    dJ = abs(J1 - J0) / max(abs(J0), 1e-300)
    dA = float(np.max(np.abs(A1 - A0)) / max(float(np.max(np.abs(A0))), 1e-300))
    return {"model": name, "n": n, "p": p, "samples": N, "hold": hold, "substeps": sub,
            "inlined_ns": 1e9 * best[True] / N, "called_ns": 1e9 * best[False] / N,
            "dJ": dJ, "dA": dA}


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--models", nargs="+", default=list(MODELS))
    args = ap.parse_args(argv)
    rows = []
    print(f"MAP sweep (A, b of Gauss–Newton over the record), least CPU time of {REPEATS}; "
          "ns a sample")
    print(f"{'model':<12} {'n':>2} {'p':>2} {'hold':<12} {'sub':>4} {'inlined':>9} "
          f"{'called':>9} {'called/inl':>10} {'ΔJ rel':>9} {'ΔA rel':>9}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in args.models:
            r = measure(name, args.samples)
            rows.append(r)
            print(f"{r['model']:<12} {r['n']:>2} {r['p']:>2} {r['hold']:<12} "
                  f"{r['substeps']:>4} {r['inlined_ns']:>9.0f} {r['called_ns']:>9.0f} "
                  f"{r['called_ns'] / r['inlined_ns']:>10.2f} {r['dJ']:>9.1e} "
                  f"{r['dA']:>9.1e}", flush=True)
    return rows


if __name__ == "__main__":
    main()
