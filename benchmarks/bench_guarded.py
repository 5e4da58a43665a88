"""The two-stage estimators against the EKF, scenario by scenario, measured against the CRLB.

Run:  .venv/bin/python benchmarks/bench_guarded.py [--seeds 20] [--t-end 20] [--jobs 2]
      [--model-seeds 8] [--no-models] [--json out/bench_guarded.json]
      [--figure out/guarded_crlb.png] [--results benchmarks/results/guarded_crlb.json]
      .venv/bin/python benchmarks/bench_guarded.py --figure-from RESULTS --figure PNG

``--results`` stores what the figure is drawn from (its curves, with the scenario table and
the run's settings) as JSON; ``--figure-from`` draws the figure from such a file without
running anything. ``make bench`` (run_all.py) rewrites the stored results of the full run,
benchmarks/results/guarded_crlb.json, from which the site's gallery draws its figure.

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
duration. The figure has one panel per scenario: the RMS over seeds of θ̂ − θ for each
estimator against √CRLB(t) (the quantity the bound bounds). The (scenario, seed) cells run in
``--jobs`` forked processes (parallel.py; default: every core), each cell's estimators one
after the other in its process.

Then, unless ``--no-models``, the same estimators off LuGre: every shipped model file by paper,
guarded, mle and ``thetahat.JointEKF(system=…).run`` through the user's entry points,
``--model-seeds`` records each (bench_models.py: RMSE over the last half ÷ √CRLB with x(0)
unknown, median t₁%, θ̂ ∈ Θ), and the measured EMPS record (bench_emps.py: θ̂'s deviation from
the published table, wall time, where the bare EKF diverges).
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
import parallel
import peers

import thetahat
from thetahat import safe_io
from thetahat.models import lugre
from thetahat.models.lugre import LuGreParameters
from thetahat.simulation.signals import Multisine

P = LuGreParameters()
THETA = P.alpha0
ESTIMATORS = ("guarded", "mle", "ekf", "paper")
#: Points per curve of the figure (log-spaced samples): ≈ 45 per decade of t over 20 s at
#: 1 kHz, more than a 400-pixel panel resolves, and few enough to store (``--results``).
FIGURE_POINTS = 200
#: Significant digits of the stored curves: the figure is a log-log plot, and the seed-to-seed
#: spread of an RMS over 20 seeds is ≈ 15 %.
STORED_DIGITS = 4


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


#: Estimators built (and numba-compiled) once per sampling period; filled in the parent before
#: the worker processes fork, so the workers inherit the compiled kernels (no compile per worker).
_EST_CACHE: dict = {}


def _estimator(name: str, dt: float):
    key = (name, dt)
    if key not in _EST_CACHE:
        if name == "paper":
            from thetahat.estimation.observer.compiled import compile_observer
            _EST_CACHE[key] = compile_observer(lugre.observer(), dt=dt)
        else:
            _EST_CACHE[key] = lugre.estimator(name, dt=dt)
    return _EST_CACHE[key]


def _diagnostics(res) -> dict:
    """The guarded run's model-error alarm over the last half: mean |θ̂₂ − θ̂_G|, mean NIS, and
    the last fit's cost per measurement (≈ 1 when the model explains the data)."""
    h = res.t >= res.t[-1] / 2
    diag = res.diagnostics
    last = diag.fits[-1] if diag.fits else None
    return {"disagreement": float(np.mean(np.abs(diag.disagreement[h]))),
            "nis": float(np.nanmean(diag.nis[h])),
            "fit_cost": float(last.cost) if last is not None else float("nan")}


def _run(name: str, sc: Scenario, traj, diag: dict | None = None
         ) -> tuple[np.ndarray, np.ndarray, float]:
    dt = round(float(traj.t[1] - traj.t[0]), 12)
    if name == "ekf":
        r = peers.run_ekf(traj.t, traj.u, traj.y, tuning=sc.ekf_tuning or
                          peers.DEFAULT_TUNING["ekf"], noise_std=0.02, x_hat0=sc.x_hat0,
                          theta_hat0=sc.theta_hat0)
        return r.theta_hat, r.x_hat, r.wall_s
    est = _estimator(name, dt)
    st = est.init(x_hat0=np.asarray(sc.x_hat0, float), theta_hat0=[sc.theta_hat0])
    t0 = time.perf_counter()
    res = est.run(traj.t, traj.u, traj.y, state0=st)
    wall = time.perf_counter() - t0
    if diag is not None and name == "guarded":
        diag.update(_diagnostics(res))
    x = getattr(res, "x_hat_refined", None)
    x = res.x_hat if x is None else x
    return np.asarray(res.theta_hat, float).reshape(-1), np.asarray(x, float), wall


def _bound(sc: Scenario, t_end: float) -> thetahat.CRLBResult:
    traj = lugre.simulate(0, t_end=t_end, noise_std=0.0, **sc.overrides)
    params = sc.overrides.get("params", P)
    return thetahat.crlb(lugre.system(params), traj.t, traj.u, theta=[THETA], noise_std=0.02)


def _cell(sc: Scenario, seed: int, t_end: float) -> dict:
    """Every estimator on one seeded record of one scenario: the per-run numbers."""
    traj = lugre.simulate(seed, t_end=t_end, **sc.overrides)
    h = traj.t >= traj.t[-1] / 2
    idx = _curve_index(traj.t.size)
    out: dict = {}
    diag: dict = {}
    for n in ESTIMATORS:
        try:
            th, x, wall = _run(n, sc, traj, diag)
            ok = bool(np.all(np.isfinite(th)))
        except thetahat.ThetahatError:
            th, x, wall, ok = (np.full(traj.t.size, np.nan),
                               np.full((traj.t.size, 2), np.nan), 0.0, False)
        m = metrics.run_metrics(traj.t, th, x, traj.x, THETA, wall, ok)
        out[n] = {"t1": metrics.settling_time(traj.t, th, THETA, 0.01),
                  "sq": float(np.sum((th[h] - THETA) ** 2)), "n": int(h.sum()),
                  "div": int(metrics.is_diverged(m, THETA)),
                  "in": bool(np.all((th >= P.theta_lower) & (th <= P.theta_upper))),
                  "us": 1e6 * wall / traj.t.size,
                  "e2": (th[idx] - THETA) ** 2}
    out["guarded"]["diag"] = diag
    return out


def _curve_index(n: int) -> np.ndarray:
    """≈ FIGURE_POINTS sample indices spaced evenly in log t (the figure's axis)."""
    return np.unique(np.geomspace(1, n - 1, FIGURE_POINTS).astype(int))


def _warm_up(scenarios, t_end: float) -> None:
    """Build and compile every estimator for every sampling period before the pool forks."""
    for sc in scenarios:
        traj = lugre.simulate(0, t_end=min(0.3, t_end), **sc.overrides)
        for n in ESTIMATORS:
            _run(n, sc, traj)


def scenario_table(seeds: int, t_end: float, log, only=None, jobs: int = 1) -> tuple[dict, dict]:
    """Every scenario × seed, the (scenario, seed) cells spread over ``jobs`` processes."""
    scenarios = [sc for sc in SCENARIOS if not only or sc.name in only]
    _warm_up(scenarios, t_end)
    with parallel.pool(jobs) as pool:
        bounds = {sc.name: pool.submit(_bound, sc, t_end) for sc in scenarios}
        cells = {sc.name: [pool.submit(_cell, sc, seed, t_end) for seed in range(seeds)]
                 for sc in scenarios}
        out: dict = {}
        curves: dict = {}
        for sc in scenarios:
            bound = bounds[sc.name].result()
            runs = [f.result() for f in cells[sc.name]]
            out[sc.name] = _summary(runs, bound)
            out[sc.name]["model_error"] = sc.model_error
            idx = _curve_index(bound.t.size)
            # RMS over seeds (what the bound bounds); a failed run's NaN is left out
            curves[sc.name] = {"t": bound.t[idx], "sqrt_crlb": bound.std[idx, 0],
                               **{n: np.sqrt(np.nanmean([r[n]["e2"] for r in runs], axis=0))
                                  for n in ESTIMATORS}}
            g, e = out[sc.name]["guarded"], out[sc.name]["ekf"]
            log(f"  {sc.name:<24} t1% guarded {_f(g['t_1pct'])} / EKF {_f(e['t_1pct'])} s   "
                f"RMSE/√CRLB guarded {g['rmse_over_crlb']:.3g} / mle "
                f"{out[sc.name]['mle']['rmse_over_crlb']:.3g} / EKF {e['rmse_over_crlb']:.3g}   "
                f"div {g['diverged']}/{e['diverged']}  θ̂∈Θ {g['in_Theta']}   alarm: "
                f"|θ̂₂ − θ̂_G| {g['disagreement']:.2g}, NIS {g['nis']:.3g}, "
                f"fit cost/meas {g['fit_cost']:.3g}")
    return out, curves


def _summary(runs: list[dict], bound) -> dict:
    half = bound.t >= bound.t[-1] / 2
    crlb_rms = math.sqrt(float(np.mean(bound.cov[half, 0, 0])))
    out: dict = {}
    for n in ESTIMATORS:
        rs = [r[n] for r in runs]
        t1 = np.array([r["t1"] for r in rs])
        mse = np.array([r["sq"] / r["n"] for r in rs])
        # seeds are the samples (one run's last-half errors are strongly correlated): the
        # standard error of the pooled RMSE relative to it, by the delta method
        rel_se = 0.5 * float(np.std(mse, ddof=1)) / math.sqrt(mse.size) / float(np.mean(mse))
        out[n] = {"t_1pct": float(np.median(t1)),
                  "t_1pct_reached": int(np.isfinite(t1).sum()),
                  "rmse_over_crlb": math.sqrt(sum(r["sq"] for r in rs)
                                              / sum(r["n"] for r in rs)) / crlb_rms,
                  "rmse_rel_se": rel_se if mse.size > 1 else float("nan"),
                  "diverged": sum(r["div"] for r in rs),
                  "in_Theta": all(r["in"] for r in rs),
                  "per_step_us": float(np.median([r["us"] for r in rs]))}
        if n == "guarded":                # medians over seeds of the model-error alarm
            for k in ("disagreement", "nis", "fit_cost"):
                out[n][k] = float(np.median([r["diag"].get(k, np.nan) for r in rs]))
    out["crlb_last_half"] = crlb_rms
    return out


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
        ekf.run(traj.t, traj.u, traj.y, state0=ekf.init(theta_hat0=[0.5]))
        best_e = min(best_e, time.perf_counter() - t0)
        t0 = time.perf_counter()
        res = est.run(traj.t, traj.u, traj.y, state0=st0)
        best_g = min(best_g, time.perf_counter() - t0)
    N = traj.t.size
    # streaming: 4 s of steps, unpaced; fits at 0.1 … 3.2 s go to the fit worker process and may
    # not all return before the stream ends (benchmarks/bench_stream.py measures paced latency)
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

    from thetahat.estimation.statistical.guarded import GuardedEstimator
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
           "fits": len(res.diagnostics.fits)}
    log(f"  cost: guarded {out['guarded_us']:.2f} µs/step amortised ({out['fits']} fits, stage 1 "
        f"compiled) ÷ compiled EKF {out['ekf_compiled_us']:.2f} µs/step = {out['ratio']:.2f}x; "
        f"streaming step {stream_us:.1f} µs (Python per-call overhead), worst single step "
        f"{out['worst_stream_step_ms']:.2f} ms with fits on the worker ({1e3 * worst0:.2f} ms "
        f"without fits) while a cold fit on 1.6 s takes {out['one_fit_1p6s_ms']:.0f} ms")
    return out


#: Line styles of the figure, per estimator: (label, colour, style, width).
STYLES = {"guarded": ("thetahat guarded", "C0", "-", 2.0), "mle": ("thetahat mle", "C1", "--", 1.4),
          "ekf": ("EKF (filterpy)", "C2", "-", 1.0), "paper": ("thetahat paper (stage 1)", "C3",
                                                                ":", 1.4)}


def figure(curves: dict, seeds: int, path: Path, log) -> None:
    """One panel per scenario: RMS over seeds of θ̂ − θ for each estimator and √CRLB(t)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log("  figure skipped: matplotlib not installed (extra 'plot')")
        return
    names = list(curves)
    cols = min(4, len(names))
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols + 0.4, 3.0 * rows + 0.9),
                             sharex=True, sharey=True, squeeze=False)
    for ax, name in zip(axes.flat, names):
        c = curves[name]
        ax.loglog(c["t"], c["sqrt_crlb"], color="k", ls="--", lw=1.2, label="√CRLB(t)")
        ax.axhline(0.01 * THETA, color="0.6", lw=0.8, ls="-.", label="1 % of θ")
        for n in ESTIMATORS:
            label, colour, style, width = STYLES[n]
            ax.loglog(c["t"], np.maximum(c[n], 1e-7), color=colour, ls=style, lw=width,
                      label=label)
        ax.set_title(name, fontsize=9)
        ax.set_ylim(1e-5, 1.0)
        ax.grid(True, which="major", lw=0.3)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    for ax in axes[:, 0]:
        ax.set_ylabel("RMS |θ̂ − θ| [N m]")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.suptitle(f"LuGre (θ = α0 = {THETA:g} N m): θ error, RMS over {seeds} seeds, against "
                 "the Cramér–Rao bound (x(0) known)", fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    log(f"  figure: {path}")


def save_results(path: Path, curves: dict, out: dict) -> None:
    """Store the figure's curves (rounded to :data:`STORED_DIGITS`, a failed run's NaN as null)
    with the scenario table and the settings of the run, as JSON (written atomically)."""
    def rounded(values) -> list:
        return [float(f"{v:.{STORED_DIGITS}g}") if math.isfinite(v) else None
                for v in np.asarray(values, dtype=float)]

    head = {"command": "benchmarks/bench_guarded.py", "seeds": out["seeds"],
            "t_end": out["t_end"], "scenarios": metrics.jsonable(out["scenarios"])}
    # one line per curve: the file stays readable and a rerun's diff shows which curves moved
    curve_lines = ",\n".join(
        f"  {json.dumps(name)}: {{\n" + ",\n".join(
            f"   {json.dumps(key)}: {json.dumps(rounded(values))}" for key, values in c.items())
        + "\n  }" for name, c in curves.items())
    text = json.dumps(head, indent=1)[:-2] + ',\n "curves": {\n' + curve_lines + "\n }\n}\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    safe_io.write_text(path, text)


def load_results(path: Path) -> tuple[dict, int]:
    """The figure's curves (arrays, null read as NaN) and the number of seeds of a file written
    by :func:`save_results`."""
    if not path.is_file():
        raise SystemExit(f"{path}: no stored results; write them with "
                         f"`python benchmarks/bench_guarded.py --no-models --results {path}` "
                         "(or `make bench`)")
    stored = json.loads(path.read_text(encoding="utf-8"))
    curves = {name: {key: np.array([np.nan if v is None else v for v in values])
                     for key, values in c.items()}
              for name, c in stored["curves"].items()}
    return curves, int(stored["seeds"])


def main(argv=None, log=print) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--t-end", type=float, default=20.0)
    ap.add_argument("--only", nargs="*", default=None, help="scenario names")
    ap.add_argument("--no-cost", action="store_true")
    ap.add_argument("--jobs", type=int, default=parallel.default_jobs(),
                    help="worker processes over the (scenario, seed) cells (default: all cores)")
    ap.add_argument("--model-seeds", type=int, default=8,
                    help="seeds per shipped model file in the every-model table (bench_models.py)")
    ap.add_argument("--no-models", action="store_true",
                    help="only the LuGre scenarios: no every-model table, no EMPS record")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=Path("out/guarded_crlb.png"))
    ap.add_argument("--results", type=Path, default=None,
                    help="store the figure's curves and the scenario table (JSON)")
    ap.add_argument("--figure-from", type=Path, default=None, metavar="RESULTS",
                    help="only draw --figure from results stored by --results")
    args = ap.parse_args(argv)
    if args.figure_from:
        curves, seeds = load_results(args.figure_from)
        figure(curves, seeds, args.figure, log)
        return {"figure": str(args.figure)}
    wall0 = time.perf_counter()
    log(f"guarded benchmark: {args.seeds} seeds × {args.t_end:g} s per scenario, "
        f"{args.jobs} processes")
    table, curves = scenario_table(args.seeds, args.t_end, log, args.only, args.jobs)
    out: dict = {"scenarios": table, "seeds": args.seeds, "t_end": args.t_end}
    if not args.no_cost:
        out["cost"] = cost(log)
    if curves:
        figure(curves, args.seeds, args.figure, log)
    if args.results:
        save_results(args.results, curves, out)
        log(f"  results: {args.results}")
    if not args.no_models:
        import bench_emps
        import bench_models
        log("\n=== every shipped model (bench_models.py)")
        out["models"] = bench_models.main(["--seeds", str(args.model_seeds)])
        log("\n=== the measured EMPS record (bench_emps.py)")
        out["emps"] = bench_emps.main([])
    log(f"bench_guarded wall time {time.perf_counter() - wall0:.0f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(metrics.jsonable(out), indent=2))
    return out



if __name__ == "__main__":
    main()
