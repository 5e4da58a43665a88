"""The two-stage estimators against the EKF, scenario by scenario, measured against the CRLB.

Run:  .venv/bin/python benchmarks/bench_guarded.py [--seeds 8] [--t-end 20] [--json out/bench_guarded.json]
      [--figure out/guarded_crlb.png]

Scenarios (the robustness set of issue 12): nominal; θ̂(0) at both edges of Θ; a wrong x̂(0)
= (3 rad/s, η_max); an overconfident EKF prior (sd 1e-3 on θ around θ̂(0) = 0.5; ours has no
covariance to set); weak excitation (u × 0.3: the motor barely breaks away, l ≡ 0); another
sampling rate (500 Hz); a model error (plant α2 × 0.8, every estimator keeps the nominal).
Estimators: ``guarded`` and ``mle`` (``lugre.estimator``), ``ekf`` (peers.run_ekf, filterpy with
the benchmark's tuning, the case's prior), ``paper`` (``lugre.observer``, compiled, for the
figure and as stage 1's reference).

Per scenario and estimator: ``t_1pct`` (median over seeds, metrics.settling_time), ``rmse_over_crlb``
(θ RMSE over the last half pooled over seeds ÷ √(mean over the last half of CRLB(t)), the
bound of the scenario's own input and sampling, x(0) known), ``diverged`` (metrics.is_diverged),
``in_Theta`` (θ̂ ∈ Θ at every sample of every run), ``per_step_us`` (median wall time per sample,
fits and stage 1 included). The cost line compares the guarded step with the compiled EKF step
(:class:`thetahat.JointEKF`, loop in numba, same model) measured in the same run, and the
largest wall time of one streaming ``step`` while fits run on the worker against the fit's
duration. The figure plots |θ̂ − θ| (median over seeds) and √CRLB(t) on the nominal scenario.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import metrics
import numpy as np
import peers

import thetahat
from thetahat.models import lugre
from thetahat.models.lugre import LuGreParameters
from thetahat.simulation.signals import Multisine

P = LuGreParameters()
THETA = P.alpha0
ESTIMATORS = ("guarded", "mle", "ekf", "paper")


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    overrides: dict = dataclasses.field(default_factory=dict)
    x_hat0: tuple = (0.0, 0.0)
    theta_hat0: float = 0.5
    ekf_tuning: Any = None
    model_error: bool = False


SCENARIOS = (
    Scenario("nominal"),
    Scenario("theta_hat0=0.05", theta_hat0=P.theta_lower),
    Scenario("theta_hat0=1", theta_hat0=P.theta_upper),
    Scenario("wrong_x_hat0", x_hat0=(3.0, P.eta_bound)),
    Scenario("overconfident_prior", ekf_tuning=dataclasses.replace(
        peers.DEFAULT_TUNING["ekf"], p0_theta=1e-3 ** 2)),
    Scenario("weak_input(u*0.3)", {"u": Multisine([0.21, 0.075], [0.5, 1.3])}),
    Scenario("fs=500", {"fs": 500.0}),
    Scenario("alpha2x0.8(model error)", {"params": dataclasses.replace(P, alpha2=0.8 * P.alpha2)},
             model_error=True),
)


def _run(name: str, sc: Scenario, traj, est_cache: dict) -> tuple[np.ndarray, np.ndarray, float]:
    dt = round(float(traj.t[1] - traj.t[0]), 12)
    if name == "ekf":
        r = peers.run_ekf(traj.t, traj.u, traj.y, tuning=sc.ekf_tuning or
                          peers.DEFAULT_TUNING["ekf"], noise_std=0.02, x_hat0=sc.x_hat0,
                          theta_hat0=sc.theta_hat0)
        return r.theta_hat, r.x_hat, r.wall_s
    key = (name, dt)
    if key not in est_cache:
        if name == "paper":
            from thetahat.estimation.compiled import compile_observer
            est_cache[key] = compile_observer(lugre.observer(), dt=dt)
        else:
            est_cache[key] = lugre.estimator(name, dt=dt)
    est = est_cache[key]
    st = est.init(x_hat0=np.asarray(sc.x_hat0, float), theta_hat0=[sc.theta_hat0])
    t0 = time.perf_counter()
    res = est.run(traj.t, traj.u, traj.y, state0=st)
    wall = time.perf_counter() - t0
    x = getattr(res, "x_hat_refined", None)
    x = res.x_hat if x is None else x
    return np.asarray(res.theta_hat, float).reshape(-1), np.asarray(x, float), wall


def _bound(sc: Scenario, t_end: float) -> thetahat.CRLBResult:
    traj = lugre.simulate(0, t_end=t_end, noise_std=0.0, **sc.overrides)
    params = sc.overrides.get("params", P)
    return thetahat.crlb(lugre.system(params), traj.t, traj.u, theta=[THETA], noise_std=0.02)


def scenario_table(seeds: int, t_end: float, log, only=None) -> tuple[dict, dict]:
    cache: dict = {}
    out: dict = {}
    curves: dict = {}
    for sc in SCENARIOS:
        if only and sc.name not in only:
            continue
        bound = _bound(sc, t_end)
        half = bound.t >= bound.t[-1] / 2
        crlb_rms = math.sqrt(float(np.mean(bound.cov[half, 0, 0])))
        rows: dict = {n: {"t1": [], "sq": [], "n": 0, "div": 0, "in": True, "us": []}
                      for n in ESTIMATORS}
        errs: dict = {n: [] for n in ESTIMATORS}
        for seed in range(seeds):
            traj = lugre.simulate(seed, t_end=t_end, **sc.overrides)
            for n in ESTIMATORS:
                try:
                    th, x, wall = _run(n, sc, traj, cache)
                    ok = bool(np.all(np.isfinite(th)))
                except thetahat.ThetahatError:
                    th, x, wall, ok = (np.full(traj.t.size, np.nan),
                                       np.full((traj.t.size, 2), np.nan), 0.0, False)
                m = metrics.run_metrics(traj.t, th, x, traj.x, THETA, wall, ok)
                r = rows[n]
                r["t1"].append(metrics.settling_time(traj.t, th, THETA, 0.01))
                h = traj.t >= traj.t[-1] / 2
                r["sq"].append(float(np.sum((th[h] - THETA) ** 2)))
                r["n"] += int(h.sum())
                r["div"] += int(metrics.is_diverged(m, THETA))
                r["in"] &= bool(np.all((th >= P.theta_lower) & (th <= P.theta_upper)))
                r["us"].append(1e6 * wall / traj.t.size)
                if sc.name == "nominal":
                    errs[n].append(np.abs(th - THETA))
        out[sc.name] = {n: {"t_1pct": float(np.median(r["t1"])),
                            "rmse_over_crlb": math.sqrt(sum(r["sq"]) / r["n"]) / crlb_rms,
                            "diverged": r["div"], "in_Theta": r["in"],
                            "per_step_us": float(np.median(r["us"]))}
                        for n, r in rows.items()}
        out[sc.name]["crlb_last_half"] = crlb_rms
        out[sc.name]["model_error"] = sc.model_error
        if sc.name == "nominal":
            curves = {"t": bound.t, "sqrt_crlb": bound.std[:, 0],
                      **{n: np.median(np.array(e), axis=0) for n, e in errs.items()}}
        g, e = out[sc.name]["guarded"], out[sc.name]["ekf"]
        log(f"  {sc.name:<24} t1% guarded {_f(g['t_1pct'])} / EKF {_f(e['t_1pct'])} s   "
            f"RMSE/√CRLB guarded {g['rmse_over_crlb']:.3g} / mle "
            f"{out[sc.name]['mle']['rmse_over_crlb']:.3g} / EKF {e['rmse_over_crlb']:.3g}   "
            f"div {g['diverged']}/{e['diverged']}  θ̂∈Θ {g['in_Theta']}")
    return out, curves


def _f(v: float) -> str:
    return "never" if not math.isfinite(v) else f"{v:.3f}"


def cost(log) -> dict:
    """Guarded step vs the compiled EKF step (same model, same data), amortised over 20 s,
    and the worst streaming step while fits run on the worker."""
    traj = lugre.simulate(0, t_end=20.0)
    ekf = thetahat.JointEKF(system=lugre.system())
    ekf.run(traj.t[:50], traj.u[:50], traj.y[:50])
    est = lugre.estimator("guarded")
    st0 = est.init(theta_hat0=[0.5])
    est.run(traj.t[:300], traj.u[:300], traj.y[:300], state0=st0)
    best_e = best_g = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        ekf.run(traj.t, traj.u, traj.y, theta_hat0=[0.5])
        best_e = min(best_e, time.perf_counter() - t0)
        t0 = time.perf_counter()
        res = est.run(traj.t, traj.u, traj.y, state0=st0)
        best_g = min(best_g, time.perf_counter() - t0)
    N = traj.t.size
    # streaming: 4 s of steps; fits at 0.1 … 3.2 s run on the worker thread
    n_stream = 4000

    def stream(estimator) -> tuple[float, float]:
        st = estimator.init(theta_hat0=[0.5])
        for k in range(40):                    # compile the streaming specialisations first
            st = estimator.step(st, traj.u[k], traj.y[k], 1e-3)
        st = estimator.init(theta_hat0=[0.5])
        worst = 0.0
        t0 = time.perf_counter()
        for k in range(n_stream):
            a = time.perf_counter()
            st = estimator.step(st, traj.u[k], traj.y[k], 1e-3)
            worst = max(worst, time.perf_counter() - a)
        return worst, time.perf_counter() - t0

    from thetahat.estimation.guarded import GuardedEstimator
    no_fits = GuardedEstimator(stage1=est.stage1, system=est.system, use_fits=False)
    worst0, _ = stream(no_fits)
    worst, elapsed = stream(est)
    stream_us = 1e6 * elapsed / n_stream
    fit_t0 = time.perf_counter()
    sched = est.fit_schedule
    prior0 = sched.initial_prior(np.zeros(2), np.array([0.5]))
    sched.fit(np.array(traj.t), np.array(traj.u), np.array(traj.y), 1601, None, prior0)
    fit_s = time.perf_counter() - fit_t0
    out = {"ekf_compiled_us": 1e6 * best_e / N, "guarded_us": 1e6 * best_g / N,
           "ratio": best_g / best_e, "stream_step_us": stream_us,
           "worst_stream_step_ms": 1e3 * worst, "one_fit_1p6s_ms": 1e3 * fit_s,
           "worst_stream_step_no_fits_ms": 1e3 * worst0,
           "fits": len(res.fits)}
    log(f"  cost: guarded {out['guarded_us']:.2f} µs/step amortised ({out['fits']} fits, stage 1 "
        f"compiled) ÷ compiled EKF {out['ekf_compiled_us']:.2f} µs/step = {out['ratio']:.2f}x; "
        f"streaming step {stream_us:.1f} µs (Python per-call overhead), worst single step "
        f"{out['worst_stream_step_ms']:.2f} ms with fits on the worker ({1e3 * worst0:.2f} ms "
        f"without fits) while a cold fit on 1.6 s takes {out['one_fit_1p6s_ms']:.0f} ms")
    return out


def figure(curves: dict, path: Path, log) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log("  figure skipped: matplotlib not installed (extra 'plot')")
        return
    fig, ax = plt.subplots(figsize=(7, 4.2))
    t = curves["t"]
    ax.loglog(t[1:], curves["sqrt_crlb"][1:], "k--", label="√CRLB(t)")
    for n in ESTIMATORS:
        ax.loglog(t[1:], np.maximum(curves[n][1:], 1e-7), label=f"|θ̂ − θ| {n} (median)")
    ax.set_ylim(1e-6, 1.0)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("N m")
    ax.set_title("LuGre, nominal: estimation error against the Cramér–Rao bound")
    ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    log(f"  figure: {path}")


def main(argv=None, log=print) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--t-end", type=float, default=20.0)
    ap.add_argument("--only", nargs="*", default=None, help="scenario names")
    ap.add_argument("--no-cost", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=Path("out/guarded_crlb.png"))
    args = ap.parse_args(argv)
    wall0 = time.perf_counter()
    log(f"guarded benchmark: {args.seeds} seeds × {args.t_end:g} s per scenario")
    table, curves = scenario_table(args.seeds, args.t_end, log, args.only)
    out: dict = {"scenarios": table, "seeds": args.seeds, "t_end": args.t_end}
    if not args.no_cost:
        out["cost"] = cost(log)
    if curves:
        figure(curves, args.figure, log)
    log(f"bench_guarded wall time {time.perf_counter() - wall0:.0f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(metrics.jsonable(out), indent=2))
    return out



if __name__ == "__main__":
    main()
