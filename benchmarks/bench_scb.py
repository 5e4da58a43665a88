"""Time of ``scb`` for n = 10 … 200 and zero agreement with SLICOT's AB08ND (via slycot).

Run:  .venv/bin/python benchmarks/bench_scb.py [--json out/bench_scb.json]

Each row: a random left-invertible system of known structure (3 chains of lengths 1–4, a χ_b
block, the rest zero dynamics) hidden behind well-conditioned changes of coordinates. Printed:
median wall time of ``scb`` and of ``invariant_zeros``, and the time ratio against slycot's
AB08ND on the same matrices (ours ÷ peer), the structure check, the largest distance between
our zeros and AB08ND's, and cond Γs against the construction's.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from thetahat import IllConditionedWarning, invariant_zeros, scb
from thetahat.testing import random_scb_system


def timed(fn, repeat: int) -> float:
    best = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best.append(time.perf_counter() - t0)
    return float(np.median(best))


def slycot_zeros(A, B, C, tol=1e-10):
    """AB08ND's finite zeros. Its default tolerance (tol=0 → n·eps-based on unscaled data)
    loses all 173 zeros of the n = 200 case; 1e-10 matches our normalised rank tolerance."""
    import slycot
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    out = slycot.ab08nd(n, m, p, A, B, C, np.zeros((p, m)), tol=tol)
    nu, Af, Bf = out[0], out[8], out[9]
    import scipy.linalg as sla
    return np.sort_complex(sla.eigvals(Af[:nu, :nu], Bf[:nu, :nu])) if nu else np.zeros(0, complex)


def zero_distance(z1, z2) -> float:
    if z1.size != z2.size:
        return float("inf")
    if z1.size == 0:
        return 0.0
    # greedy matching, relative to the zero magnitude
    rest = list(z2)
    worst = 0.0
    for z in z1:
        i = int(np.argmin([abs(z - w) for w in rest]))
        worst = max(worst, abs(z - rest.pop(i)) / max(1.0, abs(z)))
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sizes", type=int, nargs="*", default=[10, 50, 100, 200])
    args = ap.parse_args()
    try:
        import slycot  # noqa: F401
        have_slycot = True
    except ImportError:
        have_slycot = False
    rng = np.random.default_rng(2026)
    rows = []
    print(f"{'n':>5} {'scb [ms]':>9} {'zeros [ms]':>10} {'AB08ND [ms]':>11} {'zeros/AB08ND':>12} "
          f"{'structure':>9} {'|Δzero| vs AB08ND':>17} {'cond/cond_constr':>16} "
          f"{'#zeros (ours/AB08ND default tol)':>33}")
    for n in args.sizes:
        lengths = (1, 2, 4)
        n_b, r_b = max(2, n // 10), 2
        n_a = n - sum(lengths) - n_b
        ks = random_scb_system(rng, chain_lengths=lengths, n_a=n_a, n_b=n_b, r_b=r_b,
                               zeros=-rng.uniform(0.5, 5.0, n_a))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedWarning)
            repeat = 5 if n <= 100 else 3
            t_scb = timed(lambda: scb(ks.A, ks.B, ks.C), repeat)
            res = scb(ks.A, ks.B, ks.C)
        t_z = timed(lambda: invariant_zeros(ks.A, ks.B, ks.C), repeat)
        ok = (res.n_a, res.n_b, res.chain_lengths) == (ks.n_a, ks.n_b, ks.chain_lengths)
        row = dict(n=n, scb_s=t_scb, zeros_s=t_z, structure_ok=ok,
                   cond_ratio=res.condition / ks.condition,
                   zero_err_vs_construction=zero_distance(np.sort_complex(res.invariant_zeros),
                                                          ks.zeros))
        if have_slycot:
            t_s = timed(lambda: slycot_zeros(ks.A, ks.B, ks.C), repeat)
            row.update(ab08nd_s=t_s, zeros_over_ab08nd=t_z / t_s,
                       zero_err_vs_ab08nd=zero_distance(invariant_zeros(ks.A, ks.B, ks.C),
                                                        slycot_zeros(ks.A, ks.B, ks.C)),
                       ab08nd_default_tol_count=int(slycot_zeros(ks.A, ks.B, ks.C, 0.0).size))
        rows.append(row)
        print(f"{n:5d} {1e3 * t_scb:9.1f} {1e3 * t_z:10.1f} "
              f"{1e3 * row.get('ab08nd_s', float('nan')):11.1f} "
              f"{row.get('zeros_over_ab08nd', float('nan')):12.1f} {str(ok):>9} "
              f"{row.get('zero_err_vs_ab08nd', float('nan')):17.1e} {row['cond_ratio']:16.1f} "
              f"{res.n_a:>21d}/{row.get('ab08nd_default_tol_count', -1)}")
    if not have_slycot:
        print("slycot not installed: AB08ND columns skipped (pip install slycot)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
