"""Every shipped model file, every method: RMSE ÷ √CRLB and time to 1 %, in one run.

Run:  .venv/bin/python benchmarks/bench_models.py [--seeds 4] [--models prop1 ...]

For each model file of examples/ with a simulated scenario (lugre, two_inertia, prop1–prop4,
heater (minutes, 10 Hz), actuator (milliseconds, 10 kHz), spring_friction (p = 3))
and ``--seeds`` records of its own ``[scenario]`` (``thetahat.modelfile.simulate_model``),
each method through the user's entry points — ``run_estimator(spec, t, u, y, method=M)`` for
paper, guarded and mle (default settings, no trust report), ``thetahat.JointEKF(system=…)
.run(t, u, y, state0=….init(theta_hat0=…))`` for the EKF — from the file's θ̂(0):

* ``rmse/√crlb``: θ's RMSE over the last half pooled over seeds, per parameter, ÷ √(mean over
  the last half of the Cramér–Rao bound of the scenario's input and sampling with x(0)
  unknown — no estimator here is told x(0));
* ``final``: the same for the last sample's θ̂ alone ÷ √CRLB at the end (for mle the MAP
  estimate of the whole record: the seed-to-seed scatter of an efficient estimator's final
  value is this bound);
* ``t1%``: the median over seeds of the first time after which every θ̂ component stays
  within 1 % of θ (``never`` where a seed never settles: the count is printed);
* θ̂ finite and in Θ at every sample (``in Θ``).

The measured EMPS record is the subject of bench_emps.py.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import numpy as np

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
MODELS = ("lugre", "two_inertia", "prop1", "prop2", "prop3", "prop4", "heater", "actuator",
          "spring_friction")
METHODS = ("paper", "guarded", "mle", "ekf")


def run_method(spec, method: str, d) -> np.ndarray:
    import thetahat
    from thetahat.modelfile import run_estimator
    U, Y = np.asarray(d.u), np.asarray(d.y)
    if method == "ekf":
        ekf = thetahat.JointEKF(system=spec.system)
        res = ekf.run(d.t, U, Y, state0=ekf.init(theta_hat0=spec.estimator.theta_hat0))
        return np.asarray(res.theta_hat)
    return np.asarray(run_estimator(spec, d.t, U, Y, method=method, diagnose=False).theta_hat)


def bound(spec, d) -> tuple[np.ndarray, np.ndarray]:
    """The Cramér–Rao bound of θ on record ``d`` of the file's scenario, x(0) unknown:
    its mean over the last half and its value at the end, per parameter ((p,) each)."""
    import thetahat
    sc = spec.scenario
    b = thetahat.crlb(spec.system, d.t, np.asarray(d.u), theta=sc.theta,
                      noise_std=sc.noise_std, x0=sc.x0, x0_known=False)
    diag = np.diagonal(np.asarray(b.cov), axis1=-2, axis2=-1)
    return np.mean(diag[d.t.size // 2:], axis=0), diag[-1]


def efficiency(errs: list[np.ndarray], var: np.ndarray, var_end: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """RMSE ÷ √CRLB per parameter, pooled over records: over the last half (``errs``: each
    record's θ̂ − θ on its last half) and of the last sample alone."""
    ratio = np.sqrt(np.mean(np.concatenate(errs) ** 2, axis=0) / var)
    final = np.sqrt(np.mean(np.array([e[-1] for e in errs]) ** 2, axis=0) / var_end)
    return ratio, final


def settling(t1: list[float]) -> tuple[float, int]:
    """The median over records of the time to 1 % (inf unless every record settles) and how
    many settled."""
    reached = [x for x in t1 if math.isfinite(x)]
    return (float(np.median(t1)) if len(reached) == len(t1) else math.inf), len(reached)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    args = ap.parse_args(argv)
    from thetahat.modelfile import load_model, simulate_model
    from thetahat.studies.metrics import time_to_within

    out: dict = {}
    print(f"model files × methods, {args.seeds} seeds each: RMSE over the last half ÷ √CRLB "
          "(x(0) unknown) (final: the last θ̂ ÷ √CRLB at the end), median t1%")
    for name in args.models:
        spec = load_model(EXAMPLES / f"{name}.toml")
        sc = spec.scenario
        lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
        errs: dict[str, list[np.ndarray]] = {m: [] for m in METHODS}
        t1: dict[str, list[float]] = {m: [] for m in METHODS}
        inside = {m: True for m in METHODS}
        seconds = {m: 0.0 for m in METHODS}
        var = None
        for seed in range(args.seeds):
            d = simulate_model(spec, seed)
            N = d.t.size
            if var is None:
                var, var_end = bound(spec, d)
            for m in METHODS:
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    th = run_method(spec, m, d)
                seconds[m] += time.perf_counter() - t0
                inside[m] &= bool(np.all(np.isfinite(th)) and np.all((th >= lo) & (th <= hi)))
                errs[m].append(th[N // 2:] - sc.theta)
                t1[m].append(time_to_within(d.t, th, sc.theta, 0.01))
        row = {}
        for m in METHODS:
            ratio, final = efficiency(errs[m], var, var_end)
            med, reached = settling(t1[m])
            row[m] = {"rmse_over_crlb": ratio.tolist(), "final_over_crlb": final.tolist(),
                      "t_1pct": med,
                      "t_1pct_reached": reached, "in_Theta": inside[m],
                      "seconds": seconds[m]}
        out[name] = row
        cells = "  ".join(
            f"{m} {'/'.join(f'{r:.2g}' for r in row[m]['rmse_over_crlb'])}"
            f" (final {'/'.join(f'{r:.2g}' for r in row[m]['final_over_crlb'])})"
            f" t1% {row[m]['t_1pct']:.3g}s ({row[m]['t_1pct_reached']}/{args.seeds})"
            f"{'' if row[m]['in_Theta'] else ' OUT OF Θ'}" for m in METHODS)
        print(f"  {name:<12} {cells}", flush=True)
    return out


if __name__ == "__main__":
    main()
