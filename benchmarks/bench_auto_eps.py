"""``eps = "auto"``: the chosen ε's φ̂ against the best ε in hindsight, and its cost on EMPS.

Run:  nice -n 10 .venv/bin/python benchmarks/bench_auto_eps.py [--emps] [--models prop1 wheel]
      [--per-decade 6]

Default: each shipped model file in examples/ but the measured records (emps, silverbox; the
others' ``[scenario]``, given or the schema's default), one record of its scenario
(``thetahat.modelfile.simulate_model``, seed 0), whose ``PlantTrajectory.phi`` is the true φ.
``thetahat.modelfile.auto_eps`` chooses ε on the record (the file's θ̂₀, its default hold);
``thetahat.modelfile.held_run`` (θ̂ held at θ̂₀, the run the choice scores) then runs at the
chosen ε, at the file's own ε and at each ε of a log grid of ``--per-decade`` points a decade
over the same range (``EpsChoice.bounds``). φ̂'s RMS error against the true φ is taken after
the transient the criterion skips (``TRANSIENT_FRACTION`` of the record). Printed per model:
samples, the range, the chosen ε (``*``: at the range's edge) and the observer runs it took,
the file's ε, the best ε in hindsight (the grid's least RMS: the chosen ε can beat it, a ratio
below 1), RMS(chosen), RMS(best), RMS(chosen) ÷ RMS(best) and RMS(file) ÷ RMS(best); then the
least and largest ratio over the models. A file whose scenario cannot be simulated, or on
whose record ε cannot be chosen, gets a line saying why.

``--emps``: ``auto_eps`` on the measured EMPS record (examples/emps.toml, its ``[data]``
table on examples/data/emps/DATA_EMPS.mat), the chosen ε against the file's and the search's
wall time: the first call of the process (kernels compiled or loaded from the cache) and a
second.

Nothing is asserted; the figures are this machine's, from one run.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
#: Measured records: their scenarios are not what the files were written for.
MEASURED = ("emps", "silverbox")
#: The reference grid's points per decade.
PER_DECADE = 6


def shipped_models() -> list[str]:
    """The example model files but the measured records, by name."""
    return sorted(p.stem for p in EXAMPLES.glob("*.toml") if p.stem not in MEASURED)


def phi_rms(spec, d, eps: float) -> float:
    """φ̂'s RMS error against d.phi of the held run at ε, after the criterion's transient
    (inf: the observer stopped)."""
    from thetahat.estimation.observer.auto_eps import TRANSIENT_FRACTION
    from thetahat.modelfile import held_run
    u = d.u if d.u.shape[1] else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = held_run(spec, d.t, u, d.y, eps=eps)
    if res.failed_at is not None:
        return math.inf
    skip = int(TRANSIENT_FRACTION * d.t.size)
    err = np.asarray(res.phi_hat)[skip:] - np.asarray(d.phi)[skip:]
    rms = float(np.sqrt(np.mean(err ** 2)))
    return rms if math.isfinite(rms) else math.inf


def reference_grid(bounds: tuple[float, float], per_decade: int) -> np.ndarray:
    """``per_decade`` points a decade over the range, both ends included."""
    lo, hi = bounds
    if hi <= lo:
        return np.array([lo])
    count = int(math.ceil(math.log10(hi / lo) * per_decade)) + 1
    return np.geomspace(lo, hi, count)


def one_model(name: str, per_decade: int) -> dict:
    """The figures of one model file (module docstring); ``{"name", "skipped"}`` when its
    scenario cannot be simulated or ε chosen."""
    from thetahat.errors import ThetahatError
    from thetahat.modelfile import auto_eps, load_model, simulate_model
    spec = load_model(EXAMPLES / f"{name}.toml")
    if spec.scenario is None:
        return {"name": name, "skipped": "no [scenario]"}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            d = simulate_model(spec, 0)
    except (ThetahatError, ArithmeticError) as exc:
        return {"name": name, "skipped": f"its scenario cannot be simulated: {exc}"}
    try:
        choice = auto_eps(spec, d.t, d.u if d.u.shape[1] else None, d.y)
    except ThetahatError as exc:
        return {"name": name, "skipped": f"ε cannot be chosen on its record: {exc}"}
    grid = reference_grid(choice.bounds, per_decade)
    rms = np.array([phi_rms(spec, d, float(e)) for e in grid])
    best = int(np.argmin(rms))
    chosen = phi_rms(spec, d, choice.eps)
    file_rms = phi_rms(spec, d, float(spec.estimator.eps))
    return {"name": name, "N": int(d.t.size), "bounds": choice.bounds, "eps": choice.eps,
            "at_edge": choice.at_edge, "runs": len(choice.scanned),
            "eps_file": float(spec.estimator.eps), "eps_best": float(grid[best]),
            "rms_chosen": chosen, "rms_best": float(rms[best]), "rms_file": file_rms,
            "ratio": chosen / float(rms[best]), "file_ratio": file_rms / float(rms[best])}


def models_table(names: list[str], per_decade: int) -> list[dict]:
    """The default section: one line a model, then the range of the ratios."""
    print(f"eps = 'auto' on one simulated record a model (seed 0), θ̂ held at θ̂₀: φ̂'s RMS "
          f"error against the true φ, best over {per_decade} ε a decade over the range",
          flush=True)
    print(f"{'model':>16} {'N':>7} {'range':>17} {'chosen':>9} {'runs':>4} {'file':>7} "
          f"{'best':>9} {'RMS chosen':>11} {'RMS best':>10} {'ratio':>6} {'file÷best':>9}")
    rows = []
    for name in names:
        row = one_model(name, per_decade)
        rows.append(row)
        if "skipped" in row:
            print(f"{name:>16} skipped: {row['skipped']}", flush=True)
            continue
        lo, hi = row["bounds"]
        edge = "*" if row["at_edge"] else " "
        print(f"{name:>16} {row['N']:>7} {lo:>8.3g}–{hi:<8.3g} {row['eps']:>8.3g}{edge} "
              f"{row['runs']:>4} {row['eps_file']:>7.3g} {row['eps_best']:>9.3g} "
              f"{row['rms_chosen']:>11.4g} {row['rms_best']:>10.4g} {row['ratio']:>6.2f} "
              f"{row['file_ratio']:>9.2f}", flush=True)
    ratios = [r["ratio"] for r in rows if "skipped" not in r]
    if ratios:
        print(f"RMS(chosen) ÷ RMS(best) over {len(ratios)} models: {min(ratios):.2f}–"
              f"{max(ratios):.2f} (* : the chosen ε is an end of the range)")
    return rows


def emps() -> dict:
    """``--emps``: the choice on the measured record and its wall time."""
    from thetahat.io.datafile import read_data
    from thetahat.modelfile import auto_eps, load_model
    spec = load_model(EXAMPLES / "emps.toml")
    rec = read_data(EXAMPLES / "data" / "emps" / "DATA_EMPS.mat", spec.layout)
    seconds = []
    for _ in range(2):
        start = time.perf_counter()
        choice = auto_eps(spec, rec.t, rec.u, rec.y)
        seconds.append(time.perf_counter() - start)
    lo, hi = choice.bounds
    print(f"EMPS (measured, {np.asarray(rec.t).size} samples): eps = 'auto' chose "
          f"ε = {choice.eps:.3g} (file {spec.estimator.eps:g}) in [{lo:.3g}, {hi:.3g}], "
          f"{len(choice.scanned)} observer runs{', at the edge' if choice.at_edge else ''}; "
          f"search {seconds[0]:.2f} s (first call), {seconds[1]:.2f} s (second)")
    return {"eps": choice.eps, "eps_file": float(spec.estimator.eps), "bounds": choice.bounds,
            "runs": len(choice.scanned), "first_s": seconds[0], "second_s": seconds[1]}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--emps", action="store_true", help="the measured EMPS record instead")
    ap.add_argument("--models", nargs="+", default=None,
                    help="example model files by name (default: all but emps, silverbox)")
    ap.add_argument("--per-decade", type=int, default=PER_DECADE)
    args = ap.parse_args(argv)
    if args.emps:
        return {"emps": emps()}
    names = shipped_models() if args.models is None else args.models
    return {"models": models_table(names, args.per_decade)}


if __name__ == "__main__":
    main()
