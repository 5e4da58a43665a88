"""Models we do not tune for, every method: RMSE ÷ √CRLB, warnings, and the issue's targets.

Run:  .venv/bin/python benchmarks/bench_heldout.py [--seeds 4] [--models wheel ...]
      [--methods paper guarded mle ekf] [--t-scale 0.1] [--json out/heldout.json]

Stand-ins for the held-back models of the issue "Honest on a user's own model", built from
textbook physics (not copies of the held-back files): examples/wheel.toml (quarter-car wheel,
Burckhardt tyre friction, two measured speeds, p = 3), examples/cylinder.toml (pneumatic
cylinder vented through an orifice of unknown exponent, the unmeasured pressure inside g,
200 000 samples), examples/cstr.toml (jacketed CSTR, chains 2 and 4, p = 4, four hours at
1 Hz), examples/stribeck.toml (the newcomer's mass-spring with Stribeck friction), and
examples/spring_friction.toml. Each file's estimator is the newcomer's: the gradient law,
Γ = "auto", θ̂(0) at Θ's centre. The CSTR's file declares X ([state_set], Remark 1), part of
its physics like Θ: without it the paper's observer left every bound on seed 1 (g's
Arrhenius rate is Lipschitz only on bounded sets) and raised an error that says so.

For ``--seeds`` records of each file's ``[scenario]`` (``thetahat.modelfile.simulate_model``;
the CSTR's record is :func:`dac_record`: timestamps jittered, about 1 % of the output samples
missing (NaN, ``nan_policy="skip"``), the input held by a DAC between the samples), each
method runs through ``thetahat.modelfile.run_estimator(spec, t, u, y, method=M)`` with its
diagnosis (the trust report) -- with ``hold="zoh"`` on the DAC's records, the default hold on
the scenarios' smooth inputs (until 0.4 every record was run under ``hold="zoh"``, which the
statistical methods ignored then and honour now: a held input assumed for a smooth one biased
the wheel's guarded and mle to 4-18 × √CRLB) -- and prints:

* ``rmse``: θ's RMSE over the last half pooled over seeds ÷ √(mean CRLB over the last half),
  per parameter, and ``final``: the last θ̂ ÷ √CRLB at the end (bench_models.py's
  definitions and helpers; x(0) unknown);
* ``paper×sd``: the largest |θ̂ − θ| at the end ÷ the run's own reported Cramér–Rao sd
  (``result.trust.crlb_sd``), over seeds and parameters;
* ``t1%``: the median time after which every θ̂ stays within 1 % of θ (``never`` unless every
  seed settles);
* whether θ̂ stayed finite and in Θ at every sample, and the wall time over all seeds;
* the warnings the runs carried (every warning caught, by category, with the number of seeds).

The final table, "method passes target?", applies the issue's targets: guarded ≤ 1.5 ×
√CRLB (RMSE over the last half, every parameter), mle ≤ 1.3 × √CRLB (the final θ̂, the whole
record's MAP, every parameter), the paper's θ̂ within 3 × its reported Cramér–Rao sd or a
warning that says the estimate is not to be trusted (a trust-report finding or a
ConvergenceWarning) on every seed; every method must also stay finite and in Θ. The EKF has
no target (its row says whether it stayed in Θ). With 4 seeds the pooled ratios scatter by
about ±35 % (final) and less over the last half: a ratio within that of its target is a
marginal pass or fail.

``thetahat.crlb`` treats an information matrix whose smallest eigenvalue is below 1e-12 of
its largest as singular, in the parameters' own units: on the CSTR (k_ref ~ 2e-3 1/s beside
UA ~ 600 W/K) it reports an infinite bound although the problem is well posed. The bound is
then recomputed by ``thetahat.crlb`` on the model reparametrised as θ = diag(|θ*|) θ'
(:func:`scaled_bound`), and the row says so.

The first full run (4 seeds, before any fix) is kept in benchmarks/results/heldout_baseline.txt.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import bench_models

EXAMPLES = bench_models.EXAMPLES
METHODS = bench_models.METHODS
MODELS = ("wheel", "cylinder", "cstr", "stribeck", "spring_friction")
#: Models whose records are the logged kind (dac_record) rather than the plain scenario.
DAC_MODELS = ("cstr",)
#: The issue's targets: guarded's RMSE over the last half, mle's final θ̂, both ÷ √CRLB.
GUARDED_TARGET = 1.5
MLE_TARGET = 1.3
#: The paper's final θ̂ must lie within this many of its own reported Cramér–Rao sd.
PAPER_SDS = 3.0

#: The logger's timing: each sample instant is k/fs plus a normal jitter of this sd (s),
#: clipped at JITTER_CLIP, and written to the file with TIMESTAMP_RESOLUTION (s) -- a PC or
#: PLC logger at 1 Hz.
JITTER_SD = 0.03
JITTER_CLIP = 0.2
TIMESTAMP_RESOLUTION = 0.01
#: The fraction of output samples lost (NaN in y; the first and last are kept, so that x̂(0)
#: fits a sample and the record's end is defined).
MISSING_FRACTION = 0.01


class Record(NamedTuple):
    """One record: t (N,), u (N, m), y (N, r) with NaN where a sample is missing."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray


def dac_record(spec, seed: int, *, t_end: float | None = None) -> Record:
    """A logged record of the file's scenario: jittered instants, missing samples, a DAC's input.

    The logger samples y at t_k = k/fs + δ_k (δ_k ~ N(0, JITTER_SD²), clipped, rounded to
    TIMESTAMP_RESOLUTION) and writes t_k; at the same instant the DAC takes the scenario's
    multisine at t_k and holds it until t_{k+1}, so the record's u is exactly the plant's
    input under a zero-order hold on the record's own timestamps. A fraction MISSING_FRACTION
    of the y rows is NaN. The plant is the file's (``simulate_plant`` with the file's g on
    C x and its integrator), integrated on the grid of the timestamps' resolution and read at
    the t_k.

    Parameters
    ----------
    spec : ModelSpec
    seed : int
        Seeds the jitter, the missing samples and the measurement noise.
    t_end : float, optional
        Overrides the scenario's duration (s).

    Returns
    -------
    Record
    """
    from thetahat.modelfile.study import ModelPhi
    from thetahat.simulation.signals import FromArray, Multisine
    from thetahat.simulation.simulate import simulate_plant

    sc, s = spec.scenario, spec.system
    rng = np.random.default_rng([seed, 20240501])
    n_samples = int(math.floor((sc.t_end if t_end is None else t_end) * sc.fs + 1e-9)) + 1
    jitter = np.clip(rng.normal(0.0, JITTER_SD, n_samples), -JITTER_CLIP, JITTER_CLIP)
    jitter[0] = 0.0
    ticks = np.rint((np.arange(n_samples) / sc.fs + jitter) / TIMESTAMP_RESOLUTION)
    t = ticks * TIMESTAMP_RESOLUTION
    u = Multisine(sc.u_amplitudes, sc.u_frequencies)(t)
    phi = ModelPhi(perturbation=s.perturbation, C=s.C)
    plant = simulate_plant(s, phi=phi, dphi_dx=phi.dphi_dx, u=FromArray(t, u, hold="zoh"),
                           t_end=float(t[-1]), fs=1.0 / TIMESTAMP_RESOLUTION, x0=sc.x0,
                           theta=sc.theta, noise=None, method=sc.method, rtol=sc.rtol,
                           atol=sc.atol)
    x = np.asarray(plant.x)[ticks.astype(np.int64)]
    y = x @ s.C.T + rng.normal(0.0, sc.noise_std, (n_samples, s.r))
    lost = rng.random(n_samples) < MISSING_FRACTION
    lost[[0, -1]] = False
    y[lost] = np.nan
    return Record(t=t, u=u, y=y)


def record(spec, name: str, seed: int, t_end: float | None) -> Record:
    """Record ``seed`` of model ``name``: the logged kind for DAC_MODELS, else the scenario."""
    if name in DAC_MODELS:
        return dac_record(spec, seed, t_end=t_end)
    from thetahat.modelfile import simulate_model
    d = simulate_model(spec, seed, t_end=t_end)
    return Record(t=np.asarray(d.t), u=np.asarray(d.u), y=np.asarray(d.y))


def scaled_bound(spec, rec: Record) -> tuple[np.ndarray, np.ndarray]:
    """bench_models.bound on the model reparametrised as θ = diag(|θ*|) θ' (θ' = 1 at the
    truth), mapped back: the same bound, free of the units' spread in the library's singularity
    test."""
    from thetahat.model.perturbation import SymbolicPerturbation
    g, sc = spec.system.perturbation, spec.scenario
    scale = np.abs(np.asarray(sc.theta, dtype=np.float64))
    expr = g.expr.subs({sym: float(c) * sym for sym, c in zip(g.theta, scale)},
                       simultaneous=True)
    pert = SymbolicPerturbation.from_sympy(expr, u=g.u, y=g.y, x=g.x, theta=g.theta)
    system = dataclasses.replace(spec.system, perturbation=pert, parameter_set=None)
    scenario = dataclasses.replace(sc, theta=np.ones_like(scale))
    var, var_end = bench_models.bound(_Spec(system=system, scenario=scenario), rec)
    return var * scale ** 2, var_end * scale ** 2


class _Spec(NamedTuple):
    system: Any
    scenario: Any


def run(spec, method: str, rec: Record, nan_policy: str, hold: str | None) -> dict:
    """One method on one record through run_estimator, with its diagnosis and warnings
    (``hold``: the input between the samples, None for run_estimator's default)."""
    from thetahat.errors import ConvergenceWarning, ThetahatError
    from thetahat.modelfile import run_estimator
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            res = run_estimator(spec, rec.t, rec.u, rec.y, method=method, hold=hold,
                                nan_policy=nan_policy)
            error = None
        except ThetahatError as exc:
            res, error = None, f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
    seconds = time.perf_counter() - t0
    found = [(w.category.__name__, str(w.message).splitlines()[0]) for w in caught]
    trust = None if res is None else res.trust
    distrust = bool(trust is not None and trust.warnings) or any(
        issubclass(w.category, ConvergenceWarning) for w in caught)
    return {"theta_hat": None if res is None else np.asarray(res.theta_hat),
            "crlb_sd": None if trust is None else np.asarray(trust.crlb_sd),
            "warnings": found, "distrust": distrust, "error": error, "seconds": seconds}


def summarise(spec, runs: list[dict], t: list[np.ndarray], var: np.ndarray,
              var_end: np.ndarray) -> dict:
    """One method's figures over the seeds (bench_models' efficiency and settling)."""
    from thetahat.studies.metrics import time_to_within
    theta = np.asarray(spec.scenario.theta, dtype=np.float64)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    failed = [r["error"] for r in runs if r["error"] is not None]
    counts: dict[str, int] = {}
    for r in runs:
        for cat, msg in dict.fromkeys(r["warnings"]):
            counts[f"{cat}: {msg}"] = counts.get(f"{cat}: {msg}", 0) + 1
    out: dict[str, Any] = {"errors": failed, "warnings": counts,
                           "seconds": sum(r["seconds"] for r in runs)}
    done = [(r, tk) for r, tk in zip(runs, t) if r["theta_hat"] is not None]
    if not done:
        return out | {"ok": False}
    errs = [r["theta_hat"][tk.size // 2:] - theta for r, tk in done]
    ratio, final = bench_models.efficiency(errs, var, var_end)
    med, reached = bench_models.settling([time_to_within(tk, r["theta_hat"], theta, 0.01)
                                          for r, tk in done])
    inside = all(bool(np.all(np.isfinite(r["theta_hat"]))
                      and np.all((r["theta_hat"] >= lo) & (r["theta_hat"] <= hi)))
                 for r, _ in done)
    with np.errstate(divide="ignore", invalid="ignore"):
        own = [np.abs(r["theta_hat"][-1] - theta) / r["crlb_sd"] for r, _ in done]
    own_max = float(np.nanmax(own)) if np.any(np.isfinite(own)) else math.nan
    paper_ok = all(bool(np.all(o <= PAPER_SDS)) or r["distrust"] for o, (r, _) in zip(own, done))
    return out | {"ok": not failed and inside, "rmse_over_crlb": ratio, "final_over_crlb": final,
                  "own_sd_max": own_max, "paper_ok": paper_ok, "t_1pct": med,
                  "t_1pct_reached": reached, "in_Theta": inside, "seeds_run": len(done)}


def passes(method: str, row: dict) -> tuple[bool | None, str]:
    """The issue's target for ``method`` on one model's row: (passed or None, the figure)."""
    if "rmse_over_crlb" not in row:
        return False, "raised"
    if method == "guarded":
        worst = float(np.max(row["rmse_over_crlb"]))
        return row["ok"] and worst <= GUARDED_TARGET, f"{worst:.2g}"
    if method == "mle":
        worst = float(np.max(row["final_over_crlb"]))
        return row["ok"] and worst <= MLE_TARGET, f"{worst:.2g}"
    if method == "paper":
        return row["ok"] and row["paper_ok"], f"{row['own_sd_max']:.2g} sd"
    return None, "in Θ" if row["ok"] else "OUT/failed"


def fmt(v: np.ndarray) -> str:
    return "/".join(f"{x:.2g}" for x in np.asarray(v, dtype=np.float64))


def print_model(name: str, spec, rows: dict, seeds: int, note: str) -> None:
    theta = ", ".join(f"{n} = {v:g}" for n, v in zip(spec.parameter_names, spec.scenario.theta))
    print(f"\n{name}: {theta}; "
          f"{seeds} seeds{note}", flush=True)
    print(f"  {'method':<8} {'rmse/√crlb':<22} {'final/√crlb':<22} {'paper×sd':>9} "
          f"{'t1%':>9} {'in Θ':>5} {'wall s':>7}")
    for m, row in rows.items():
        if "rmse_over_crlb" not in row:
            print(f"  {m:<8} raised on every seed: {row['errors'][0]}")
            continue
        t1 = (f"{row['t_1pct']:.3g}s" if math.isfinite(row["t_1pct"])
              else f"never({row['t_1pct_reached']})")
        print(f"  {m:<8} {fmt(row['rmse_over_crlb']):<22} {fmt(row['final_over_crlb']):<22} "
              f"{row['own_sd_max']:>9.3g} {t1:>9} {'yes' if row['in_Theta'] else 'NO':>5} "
              f"{row['seconds']:>7.1f}")
        for e in row["errors"]:
            print(f"           raised: {e}")
    for m, row in rows.items():
        for text, count in row["warnings"].items():
            print(f"    {m} warned ({count}/{seeds}): {text[:240]}")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument("--methods", nargs="*", default=list(METHODS))
    ap.add_argument("--t-scale", type=float, default=1.0,
                    help="fraction of each scenario's duration (short runs while developing)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = ap.parse_args(argv)
    from thetahat.modelfile import load_model
    from thetahat.safe_io import write_text

    print(f"held-out models × methods, {args.seeds} seeds, t × {args.t_scale:g}: RMSE over "
          "the last half ÷ √CRLB (final: the last θ̂ ÷ √CRLB at the end), paper×sd: the "
          "largest |θ̂ − θ| at the end ÷ the run's own Cramér–Rao sd", flush=True)
    table: dict[str, dict] = {}
    for name in args.models:
        spec = load_model(EXAMPLES / f"{name}.toml")
        t_end = None if args.t_scale == 1.0 else spec.scenario.t_end * args.t_scale
        nan_policy = "skip" if name in DAC_MODELS else "raise"
        # a DAC's record is held between its samples; the scenarios' inputs are smooth
        # signals, for which run_estimator's default (linear for the statistical methods)
        # is the closer description
        hold = "zoh" if name in DAC_MODELS else None
        runs: dict[str, list[dict]] = {m: [] for m in args.methods}
        ts, note = [], ""
        var = var_end = None
        for seed in range(args.seeds):
            rec = record(spec, name, seed, t_end)
            ts.append(rec.t)
            if var is None:
                var, var_end = bench_models.bound(spec, rec)
                if not np.all(np.isfinite(var_end)):
                    var, var_end = scaled_bound(spec, rec)
                    note = " (thetahat.crlb singular in the file's units: bound in θ's scale)"
            for m in args.methods:
                runs[m].append(run(spec, m, rec, nan_policy, hold))
        rows = {m: summarise(spec, runs[m], ts, var, var_end) for m in args.methods}
        print_model(name, spec, rows, args.seeds, note)
        table[name] = rows
    print("\nmethod passes target? (guarded: RMSE last half ≤ "
          f"{GUARDED_TARGET} √CRLB; mle: final ≤ {MLE_TARGET} √CRLB; paper: within "
          f"{PAPER_SDS:g} of its own sd or a trust warning; all: finite, in Θ)")
    print(f"  {'model':<16}" + "".join(f"{m:>18}" for m in args.methods))
    for name, rows in table.items():
        cells = []
        for m in args.methods:
            ok, figure = passes(m, rows[m])
            mark = "—" if ok is None else ("yes" if ok else "NO")
            cells.append(f"{mark + ' (' + figure + ')':>18}")
        print(f"  {name:<16}" + "".join(cells))
    if args.json is not None:
        plain = json.dumps(table, indent=1, default=lambda o: np.asarray(o).tolist())
        write_text(args.json, plain)
    return table


if __name__ == "__main__":
    main()
