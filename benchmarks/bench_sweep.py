"""Cost of an ε sweep: one SCB per design family (EstimatorSpec) vs a redesign for every run.

Run:  .venv/bin/python benchmarks/bench_sweep.py [--t-end 0.5] [--seeds 2] [--repeat 3]

The same ε sweep of the LuGre example (10 values of ε, the same seeds and records) is run
twice in this process:

* "redesign per run": ``eps_sweep(lugre.observer, ...)`` — what every sweep did before the
  estimator spec: each (ε, seed) run designs K(ε) and the second observer's gain again, two
  SCBs per run;
* "one spec": ``eps_sweep(lugre.estimator_spec(), ...)`` — K(ε) from ``GainDesign.at(eps)``
  on the spec's SCB.

Printed: the number of SCB computations of each (counted by wrapping ``scb`` for the run),
the best-of-``repeat`` wall time of each (the two alternate, so that load on the machine hits
both alike) and their ratio; then the same for the assembly alone (building the observers of
the sweep, without running them), where the SCBs are the whole cost. Records are short by default so
that the design's share of the sweep is visible; with the default 20 s records the runs
dominate and the two agree to within noise.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from thetahat.design import gains
from thetahat.models import lugre
from thetahat.studies.sweep import eps_sweep

EPS = (1.0, 0.8, 0.6, 0.5, 0.4, 0.3, 0.2, 0.15, 0.1, 0.05)


@contextmanager
def counted_scb() -> Iterator[list[int]]:
    """Count the calls of ``scb`` made by the gain designs inside the block."""
    count = [0]
    original = gains.scb

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        count[0] += 1
        return original(*args, **kwargs)

    gains.scb = wrapped  # type: ignore[assignment]
    try:
        yield count
    finally:
        gains.scb = original  # type: ignore[assignment]


def best_times(fns: list[Callable[[], Any]], repeat: int) -> list[float]:
    """Best-of-``repeat`` wall time of each function, the functions alternating."""
    best = [float("inf")] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            best[i] = min(best[i], time.perf_counter() - t0)
    return best


def main(argv: list[str] | None = None) -> dict[str, float]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=0.5, help="record length in s")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    simulate = functools.lru_cache(maxsize=None)(
        functools.partial(lugre.simulate, t_end=args.t_end))
    seeds = range(args.seeds)
    for s in seeds:                       # simulate once, outside the timing
        simulate(s)

    def per_run() -> Any:
        return eps_sweep(lugre.observer, simulate, EPS, seeds, theta_hat0=[0.5],
                         progress=False)

    def one_spec() -> Any:
        return eps_sweep(lugre.estimator_spec(), simulate, EPS, seeds, theta_hat0=[0.5],
                         progress=False)

    def build_per_run() -> Any:
        return [lugre.observer(e) for e in EPS for _ in seeds]

    def build_spec() -> Any:
        spec = lugre.estimator_spec()
        return [spec.build(e) for e in EPS for _ in seeds]

    with counted_scb() as n_old:
        per_run()
    with counted_scb() as n_new:
        one_spec()
    t_old, t_new = best_times([per_run, one_spec], args.repeat)
    b_old, b_new = best_times([build_per_run, build_spec], 5 * args.repeat)
    print(f"eps sweep of the LuGre example: {len(EPS)} eps x {args.seeds} seed(s), "
          f"{args.t_end:g} s records at 1 kHz (simulated once, not timed)")
    print(f"  {'':18s} {'SCBs':>5s} {'sweep [s]':>10s} {'assembly [s]':>13s}")
    print(f"  {'redesign per run':18s} {n_old[0]:5d} {t_old:10.3f} {b_old:13.4f}")
    print(f"  {'one spec':18s} {n_new[0]:5d} {t_new:10.3f} {b_new:13.4f}")
    print(f"  ratio (redesign per run / one spec): sweep {t_old / t_new:.3f}, "
          f"assembly {b_old / b_new:.1f}")
    return {"scb_per_run": n_old[0], "scb_spec": n_new[0], "sweep_per_run_s": t_old,
            "sweep_spec_s": t_new, "assembly_per_run_s": b_old, "assembly_spec_s": b_new}


if __name__ == "__main__":
    main()
