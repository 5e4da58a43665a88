"""Each method on the Silverbox training split, validated on the test splits, against the
output-error fit of the same model.

Run:  nice -n 10 .venv/bin/python benchmarks/bench_silverbox.py [--train N] [--hold H]
      [--methods M ...] [--stage2-h-rho R]

The shipped model file (examples/silverbox.toml) on the Silverbox record (Wigren & Schoukens
2013; 131 072 samples at 610.35 Hz) through ``thetahat.models.silverbox_report`` (the path of
``thetahat demo silverbox``): ``paper``, ``guarded``, ``mle`` and the joint EKF estimate θ on
the training split [40650, 105712), and each θ̂ is scored by the benchmark's protocol: a free
run of each test split from x(0) fitted on its first 50 samples, RMS in mV and fit in %
(``thetahat.models.silverbox.validate``). Every kernel is compiled first by a run on a short
cut, so the times printed are warm. The peers: the output-error fit of the same model
(``thetahat.studies.validation.fit_output_error``, a converged simulator) under each input
reconstruction (zero-order, linear, band-limited), and the published figures of
``thetahat.models.silverbox.LITERATURE``. Printed: θ̂ ± its Cramér–Rao sd per method, the test
RMS and fit per split, each RMS as a ratio to the output-error fit with the methods' hold
(the issue's target: ≤ 1.15), and the wall times.

``--stage2-h-rho R``: also ``mle`` with stage 2's RK4 sub-steps bounded by h ρ ≤ R instead of
the default 2 (``FitSchedule(h_rho=R)``): what a converged stage-2 simulator changes.
``--train N``: the first N samples of the training split only (a quick look).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings

import numpy as np


def stage2_substeps(h_rho: float, train_samples: int | None) -> dict:
    """``mle`` with stage 2's sub-steps bounded by h ρ ≤ h_rho, validated like the others."""
    from thetahat.estimation.statistical.map_fit import FitSchedule
    from thetahat.estimation.statistical.mle import MapEstimator
    from thetahat.io.datafile import read_data
    from thetahat.modelfile import load_model, start_x_hat
    from thetahat.models import silverbox
    spec = load_model(silverbox.MODEL_FILE)
    train = read_data(silverbox.DATA_FILE, spec.layout)
    if train_samples is not None:
        train = train.segment(0, min(train_samples, train.t.size))
    est = MapEstimator(system=spec.system,
                       schedule=FitSchedule(system=spec.system, h_rho=h_rho))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = est.run(train.t, train.u, train.y,
                      state0=est.init(x_hat0=start_x_hat(spec, train.y),
                                      theta_hat0=spec.estimator.theta_hat0))
    seconds = time.perf_counter() - t0
    theta = res.theta_hat[-1]
    check = silverbox.validate(theta, hold="foh")
    rms = {s.name: 1e3 * float(s.rms[0]) for s in check.scores}
    print(f"  mle with stage 2's h ρ ≤ {h_rho:g}: {seconds:.1f} s, θ̂ = "
          f"{np.array2string(theta, precision=5)}, test RMS "
          + ", ".join(f"{v:.3g}" for v in rms.values()) + " mV (hold 'foh')")
    return {"h_rho": h_rho, "seconds": seconds, "theta": theta.tolist(), "rms_mV": rms}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=int, default=None,
                    help="estimate from the first N training samples only")
    ap.add_argument("--hold", choices=["zoh", "foh", "bandlimited"], default="foh",
                    help="the methods' hold and their validation's (default foh)")
    ap.add_argument("--methods", nargs="+", default=None,
                    help="a subset of the methods (default: all)")
    ap.add_argument("--stage2-h-rho", type=float, default=None,
                    help="also mle with stage 2's sub-steps at h ρ ≤ this")
    args = ap.parse_args(argv)
    from thetahat.models import silverbox
    from thetahat.models.silverbox_report import METHODS, report

    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        methods = tuple(args.methods or METHODS)
        report(out=tmp, methods=methods, references=(), train_samples=1000, hold=args.hold,
               verbose=False)                                        # warm-up: kernels
        t0 = time.perf_counter()
        done = report(out=tmp, methods=methods, references=("zoh", "foh", "bandlimited"),
                      train_samples=args.train, hold=args.hold, verbose=False)
        total = time.perf_counter() - t0
    print(f"Silverbox (Wigren & Schoukens 2013), {total:.0f} s in all")
    print(done.table())
    for run in done.runs:
        if run.warnings:
            print(f"{run.name}: " + " | ".join(w[:160] for w in run.warnings))
    ref = done.reference()
    out: dict = {"train": list(done.train), "hold": done.hold, "total_seconds": total}
    for item in done.runs + done.references:
        out[item.name] = {
            "theta": item.theta.tolist(), "sd": item.sd.tolist(), "in_theta": item.in_theta,
            "seconds": item.seconds,
            "rms_mV": {s: item.rms_mV(s) for s in silverbox.TEST_SPLITS},
            "fit_percent": {s: float(item.validation[s].fit_percent[0])
                            for s in silverbox.TEST_SPLITS},
            "ratio_to_oe": ({s: item.rms_mV(s) / ref.rms_mV(s) for s in silverbox.TEST_SPLITS}
                            if ref is not None else None)}
    if args.stage2_h_rho is not None:
        out["stage2_h_rho"] = stage2_substeps(args.stage2_h_rho, args.train)
    return out


if __name__ == "__main__":
    main()
