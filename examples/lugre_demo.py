"""The paper's DC motor with LuGre friction (Sec. VIII): structural report.

Run:  make demo   (or: .venv/bin/python examples/lugre_demo.py --no-show)

Prints, for the true motor (σ1 = 0.6) and for the design system (σ1 = 0): Assumption 1, the
SCB of the extended error system (4) and the gains K(ε = 1) of Sec. VIII.
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

import thetahat as th

J, SIGMA0, ALPHA2 = 0.0023, 260.0, 0.176


def linear_part(sigma1: float):
    A = np.array([[-(ALPHA2 + sigma1) / J, -SIGMA0 / J], [1.0, 0.0]])
    E = np.array([[sigma1 / J], [-1.0]])
    C = np.array([[1.0, 0.0]])
    return A, E, C


def report(sigma1: float) -> None:
    A, E, C = linear_part(sigma1)
    print(f"=== DC motor, sigma1 = {sigma1} ===")
    print(th.check_assumption_1(A, E, C))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sc = th.scb(*th.extended_system(A, E, C))
    print(f"SCB of the error system (4): {sc}")
    for w in caught:
        print(f"  warning: {w.message}")
    d = th.modified_high_gain(A, E, C, eps=1.0)
    print(f"K(eps=1), poles -1, -2, ...: {np.array2string(d.K.ravel(), precision=6)}")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-show", action="store_true", help="headless (nothing to show yet)")
    ap.parse_args()
    for s1 in (0.6, 0.0):
        report(s1)
    A0, E0, C = linear_part(0.0)
    A, E, _ = linear_part(0.6)
    d = th.modified_high_gain(A0, E0, C, eps=1.0)
    print("Design on sigma1 = 0, applied to sigma1 = 0.6 (Sec. VII-VIII):")
    print(th.apply_design(d, A, E, C))


if __name__ == "__main__":
    main()
