"""The trust report's process-noise search: a short head first against one long search.

Run:  nice -n 10 .venv/bin/python benchmarks/bench_q_search.py

``likelihood.search_process_noise`` searches q at a fixed θ on the record's first
``Q_FIRST_HEAD`` samples and goes on to ``Q_SEARCH_SAMPLES`` only when the short head leaves
log₁₀ q̂ more than ``Q_XTOL`` uncertain; ``first_head=Q_SEARCH_SAMPLES`` is the one long
search it replaced. Printed per record, both measured in this run (warm: each model's kernels
run once on a short cut first): q̂ / q₀ of each, the samples the short search ended on, the
gap in decades and the ratio of the long search's time to the short one's. The records: the
measured EMPS (published θ) and Silverbox training split (the first 3·2¹³ samples, an
output-error θ, band-limited hold), and four shipped model files simulated for 3·2¹² samples
at θ 5 % off their truth (a model error, so that q matters).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("lugre", "two_inertia", "actuator", "spring_friction")
#: An output-error fit's θ on the Silverbox training split (benchmarks/bench_silverbox.py).
SILVERBOX_THETA = (5.369e-06, 2.252e-04, 0.9893, 3.915, 6.17e-03)


def cases():
    """(name, spec, t, u, y, θ, hold) of each record."""
    from thetahat.io.datafile import read_data
    from thetahat.modelfile import load_model, simulate_model
    from thetahat.models import emps, silverbox
    spec = load_model(ROOT / "examples" / "emps.toml")
    rec = emps.load()
    yield "emps", spec, rec.t, rec.u, rec.y, emps.PUBLISHED.value, "foh"
    spec = load_model(silverbox.MODEL_FILE)
    rec = read_data(silverbox.DATA_FILE, spec.layout).segment(0, 3 * 2 ** 13)
    yield "silverbox", spec, rec.t, rec.u, rec.y, np.array(SILVERBOX_THETA), "bandlimited"
    for name in MODELS:
        spec = load_model(ROOT / "examples" / f"{name}.toml")
        d = simulate_model(spec, 3, t_end=3 * 2 ** 12 / spec.scenario.fs)
        yield name, spec, d.t, d.u, d.y, np.asarray(spec.scenario.theta) * 1.05, "foh"


def main() -> list[dict]:
    import thetahat.estimation.statistical.likelihood as lk
    from thetahat.estimation.statistical.input_hold import stage2_samples
    from thetahat.estimation.statistical.noise_level import estimate_noise_std
    warnings.simplefilter("ignore")
    rows = []
    print(f"{'record':16s} {'N':>6s}  {'short q/q0':>10s} {'on':>6s}  {'long q/q0':>10s} "
          f"{'on':>6s}  {'gap [dec]':>9s}  {'long/short time':>15s}")
    for name, spec, t, u, y, theta, hold in cases():
        t = np.asarray(t, dtype=float)
        N = t.size
        U = np.ascontiguousarray(stage2_samples(np.asarray(u, float).reshape(N, -1), hold)[0])
        Y = np.asarray(y, dtype=float).reshape(N, -1)
        system = spec.system
        x0 = np.concatenate([Y[0, :1], np.zeros(system.n - 1)])
        sigma = estimate_noise_std(Y)
        kw = dict(theta=theta, x_hat0=x0, x_sd=np.full(system.n, 10.0), noise_std=sigma,
                  hold=hold)
        lk.search_process_noise(system, t[:300], U[:300], Y[:300], **kw)     # compile
        t0 = time.perf_counter()
        short = lk.search_process_noise(system, t, U, Y, **kw)
        t_short = time.perf_counter() - t0
        t0 = time.perf_counter()
        long = lk.search_process_noise(system, t, U, Y, first_head=lk.Q_SEARCH_SAMPLES, **kw)
        t_long = time.perf_counter() - t0
        q0 = lk.process_noise_scale(system, float(np.median(np.diff(t))), sigma)
        gap = (abs(float(np.log10(short.q / long.q))) if short.q > 0 and long.q > 0
               else (0.0 if short.q == long.q else float("inf")))
        print(f"{name:16s} {N:6d}  {short.q / q0:10.3g} {short.samples:6d}  "
              f"{long.q / q0:10.3g} {long.samples:6d}  {gap:9.3f}  {t_long / t_short:15.1f}")
        rows.append({"record": name, "N": N, "short_q_over_q0": short.q / q0,
                     "short_samples": short.samples, "long_q_over_q0": long.q / q0,
                     "gap_decades": gap, "time_ratio": t_long / t_short})
    return rows


if __name__ == "__main__":
    main()
