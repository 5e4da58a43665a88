"""The paper's example end to end: DC motor with LuGre friction (Sec. VIII), Fig. 1.

Run:  make demo   (or: .venv/bin/python examples/lugre_demo.py --no-show)

Prints the structural report (Assumption 1, SCB for σ1 = 0.6 and 0), the gains K(ε = 1)
designed on the σ1 = 0 design system, then runs the paper's observer on the default scenario
and writes out/lugre.png (the four panels of Fig. 1) and out/lugre.json (the summary).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from thetahat.models.lugre_report import report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-show", action="store_true", help="do not open a window")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eps", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path("out"))
    args = ap.parse_args()
    report(out=args.out, eps=args.eps, seed=args.seed, show=not args.no_show)


if __name__ == "__main__":
    main()
