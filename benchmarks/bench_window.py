"""Bounded fits (``window``) against fits of all the data: cost on LuGre, efficiency on models.

Run:  .venv/bin/python benchmarks/bench_window.py [--cost] [--efficiency] [--sizes 10000 100000]
      [--models prop1 heater actuator spring_friction two_inertia prop2 prop3 prop4] [--seeds 4]
      [--method mle|guarded] [--t-end SECONDS] [--records]

``--cost`` (default when neither is given): LuGre records (``thetahat.models.lugre.simulate``,
1 kHz) of each size (default 10⁴ and 10⁵; add 1000000 to ``--sizes`` for 10⁶, ≈ 2 min of
simulation and minutes of full-record fits). Measured in this run, with the compiled kernels,
after a warm-up on 2 000 samples: the joint EKF's pass (:class:`JointEKF`, the reference),
then :class:`MapEstimator` with ``window=None`` (fits of all the data so far) and with
``window="auto"``. Printed per size: seconds and ratio to the EKF's pass, the fits, the longest
fit and the median fit (from the ``fit_progress`` callbacks' timestamps: a fit's latency, in
the caller), each also as a ratio to the EKF's pass over the same record; then each variant's
log-log slope of total seconds against N (1: linear) and of the longest fit against N (0:
bounded).

``--efficiency``: per model file, ``--seeds`` runs of its ``[scenario]``
(``thetahat.modelfile.simulate_model``) by the MAP estimator with and without the window,
x̂(0) as the model-file path starts it (``start_x_hat``: from the first outputs):
the RMSE of θ̂ over the last half ÷ √(mean Cramér–Rao bound there, x(0) unknown), per
component, and the ratio window ÷ all the data (the same records: the window's own loss).
``--method guarded``: the same for the model file's guarded estimator
(``thetahat.modelfile.run_estimator``, the file's gains and hold). ``--t-end``: the scenarios
simulated to that time instead of their own end (EMPS's scenario, 2 001 samples, is shorter
than any window: ``--models emps --t-end 25`` gives the measured record's length).

``--records``: the measured records (EMPS, whole; the Silverbox's training split) through
``thetahat.modelfile.run_estimator`` by ``mle`` and ``guarded`` with and without the window:
seconds, fits, θ̂, the benchmark's validation (EMPS: the closed loop's relative errors; the
Silverbox: free-run RMS on the three test splits, linear hold), and the window's θ̂ − all the
data's in the last fit's standard errors.

Nothing is asserted; the figures are this machine's, from one run.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent / "examples"
WARMUP = 2_000
MODELS = ("prop1", "heater", "actuator", "spring_friction", "two_inertia", "prop2", "prop3",
          "prop4")


def _timed_map(est, d, theta0):
    """(seconds, fit latencies, result) of one MapEstimator run."""
    stamps = []
    start = time.perf_counter()
    res = est.run(d.t, d.u, d.y, state0=est.init(theta_hat0=theta0),
                  fit_progress=lambda done, total: stamps.append(time.perf_counter()))
    total = time.perf_counter() - start
    return total, np.diff(stamps), res


def cost(sizes: list[int]) -> None:
    """The cost table (module docstring)."""
    from thetahat.estimation.statistical.ekf import JointEKF
    from thetahat.estimation.statistical.mle import MapEstimator
    from thetahat.models import lugre
    sys_ = lugre.system()
    ekf = JointEKF(system=sys_, compiled=True)
    variants = {"all data": MapEstimator(system=sys_, compiled=True),
                "window": MapEstimator(system=sys_, compiled=True, window="auto")}
    d = lugre.simulate(seed=0, t_end=(WARMUP - 1) / 1000.0)
    ekf.run(d.t, d.u, d.y, state0=ekf.init(theta_hat0=[0.5]))
    for est in variants.values():
        _timed_map(est, d, [0.5])
    rows: dict[str, list[tuple[int, float, float]]] = {k: [] for k in variants}
    print(f"{'N':>9} {'variant':>9} {'s':>8} {'÷EKF':>7} {'fits':>5} {'W':>6} "
          f"{'max fit s':>10} {'÷EKF':>7} {'median fit s':>13} {'θ̂(end)':>10} {'sd':>9}")
    for N in sizes:
        d = lugre.simulate(seed=0, t_end=(N - 1) / 1000.0)
        start = time.perf_counter()
        ekf.run(d.t, d.u, d.y, state0=ekf.init(theta_hat0=[0.5]))
        t_ekf = time.perf_counter() - start
        print(f"{N:>9} {'EKF':>9} {t_ekf:>8.3f} {1.0:>7.2f}")
        for name, est in variants.items():
            total, lat, res = _timed_map(est, d, [0.5])
            fits = res.diagnostics.fits
            W = max((f.k1 for f in fits if f.k0 == 0), default=0) if name == "window" else N
            rows[name].append((N, total, float(lat.max())))
            print(f"{N:>9} {name:>9} {total:>8.3f} {total / t_ekf:>7.2f} {len(fits):>5} "
                  f"{W:>6} {lat.max():>10.4f} {lat.max() / t_ekf:>7.3f} "
                  f"{np.median(lat):>13.5f} {res.theta_hat[-1, 0]:>10.6f} "
                  f"{res.diagnostics.theta_sd[-1, 0]:>9.2e}", flush=True)
    if len(sizes) > 1:
        for name, r in rows.items():
            n, tot, mx = (np.array(c, dtype=float) for c in zip(*r))
            slope = np.polyfit(np.log(n), np.log(tot), 1)[0]
            slope_fit = np.polyfit(np.log(n), np.log(mx), 1)[0]
            print(f"{name}: log-log slope of total seconds vs N {slope:.2f}, "
                  f"of the longest fit {slope_fit:.2f}")


def efficiency(models: list[str], seeds: int, method: str = "mle",
               t_end: float | None = None) -> None:
    """The efficiency table (module docstring)."""
    import thetahat
    from thetahat.estimation.statistical.mle import MapEstimator
    from thetahat.modelfile import load_model, run_estimator, simulate_model, start_x_hat
    for name in models:
        spec = load_model(EXAMPLES / f"{name}.toml")
        sc = spec.scenario
        d = simulate_model(spec, 0, t_end=t_end)
        N = d.t.size
        b = thetahat.crlb(spec.system, d.t, np.asarray(d.u), theta=sc.theta,
                          noise_std=sc.noise_std, x0=sc.x0, x0_known=False)
        var = np.mean(np.diagonal(np.asarray(b.cov), axis1=-2, axis2=-1)[N // 2:], axis=0)
        rmse = {}
        for window in (None, "auto"):
            est = MapEstimator(system=spec.system, window=window)
            errs, W = [], 0
            for seed in range(seeds):
                d = simulate_model(spec, seed, t_end=t_end)
                if method == "mle":
                    res = est.run(d.t, np.asarray(d.u), np.asarray(d.y),
                                  state0=est.init(x_hat0=start_x_hat(spec, np.asarray(d.y)),
                                                  theta_hat0=spec.estimator.theta_hat0))
                else:                   # the model file's estimator, its gains and hold
                    res = run_estimator(spec, d.t, d.u, d.y, method=method, window=window,
                                        diagnose=False)
                errs.append(res.theta_hat[N // 2:] - sc.theta)
                W = max(f.k1 for f in res.diagnostics.fits if f.k0 == 0)
            rmse[window] = np.sqrt(np.mean(np.concatenate(errs) ** 2, axis=0))
            label = "all data" if window is None else f"window W={W}"
            bound = (f"RMSE/√CRLB {np.round(rmse[window] / np.sqrt(var), 3).tolist()}"
                     if np.all(np.isfinite(var)) else
                     f"RMSE {np.array2string(rmse[window], precision=3)} (this call's bound "
                     "is not finite: the ratio below is the figure)")
            print(f"{name:>16} N={N:<6} {label:>14}: {bound}", flush=True)
        ratio = rmse["auto"] / np.where(rmse[None] > 0, rmse[None], math.nan)
        print(f"{name:>16} window ÷ all data: {np.round(ratio, 3).tolist()}", flush=True)


def records(methods: list[str]) -> None:
    """The measured records' table (module docstring)."""
    from thetahat.io.datafile import read_data
    from thetahat.modelfile import load_model, run_estimator
    from thetahat.models import emps, silverbox
    from thetahat.models.emps_report import MODEL_FILE as EMPS_FILE
    cases = (("EMPS", load_model(EMPS_FILE), emps.load(), emps.validate),
             ("Silverbox train", load_model(silverbox.MODEL_FILE), None,
              lambda th: silverbox.validate(th, hold="foh")))
    for name, spec, rec, validate in cases:
        if rec is None:                 # the file's [data] reads the training split
            rec = read_data(silverbox.DATA_FILE, spec.layout)
        for method in methods:
            out = {}
            for window in (None, "auto"):
                start = time.perf_counter()
                res = run_estimator(spec, rec.t, rec.u, rec.y, method=method, window=window,
                                    diagnose=False)
                seconds = time.perf_counter() - start
                fits = res.diagnostics.fits
                W = max((f.k1 for f in fits if f.k0 == 0), default=0)
                se = np.sqrt(np.diag(fits[-1].cov)[-spec.system.p:])
                out[window] = (res.theta_hat[-1], se)
                check = validate(res.theta_hat[-1])
                score = (f"test RMS {', '.join(f'{1e3 * float(c.rms[0]):.3f}' for c in check.scores)} mV"
                         if hasattr(check, "scores") else
                         f"validation errors {check.position:.3g} / {check.velocity:.3g} / "
                         f"{check.force:.3g} %")
                label = "all data" if window is None else f"window W={W}"
                print(f"{name:>16} {method:>8} {label:>14}: {seconds:6.1f} s, {len(fits)} fits, "
                      f"θ̂ {np.array2string(res.theta_hat[-1], precision=5)}, {score}",
                      flush=True)
            shift = (out["auto"][0] - out[None][0]) / out[None][1]
            print(f"{name:>16} {method:>8} window − all data, in the last fit's standard "
                  f"errors: {np.round(shift, 2).tolist()}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cost", action="store_true")
    ap.add_argument("--efficiency", action="store_true")
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--models", nargs="+", default=list(MODELS))
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--method", choices=("mle", "guarded"), default="mle")
    ap.add_argument("--records", action="store_true")
    ap.add_argument("--t-end", type=float, default=None,
                    help="simulate each scenario to this time (s) instead of its own end")
    a = ap.parse_args()
    warnings.simplefilter("ignore")      # the figures, not the estimates' warnings
    if a.records:
        records(["mle", "guarded"])
    if a.cost or not (a.efficiency or a.records):
        cost(a.sizes)
    if a.efficiency:
        efficiency(a.models, a.seeds, a.method, a.t_end)


if __name__ == "__main__":
    main()
