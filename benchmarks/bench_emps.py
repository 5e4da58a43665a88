"""Each method on the measured EMPS record, against the benchmark's own least squares.

Run:  .venv/bin/python benchmarks/bench_emps.py

The shipped model file (examples/emps.toml) on DATA_EMPS (24 841 samples at 1 kHz, 24.84 s) by
``paper``, ``guarded`` and ``mle`` through ``thetahat.models.emps_report`` (the path of
``thetahat demo emps``: read the MAT file through the ``[data]`` table, ``run_estimator``,
validation), after one warm-up run so that every kernel is in the cache. The peer is the
benchmark's own identification, IDIM-LS: a zero-phase Butterworth filter of q, central
differences for q̇ and q̈, and one linear least squares τ = M q̈ + Fv q̇ + Fc sign(q̇) + offset
(the description's section 3.4) — ten lines of NumPy/SciPy that reproduce the published table
to ≈ 0.1 %. Printed, one run: each method's wall time, its ratio to the record's duration
(real-time factor) and to IDIM-LS's, and θ̂'s deviation from the published values; the same
for ``thetahat.JointEKF(system=…).run`` with its defaults (the model taken as exact: on this
record it diverges, and the line says where); and the
output-error MAP fit of the whole record (the model taken as exact), whose cost per measurement
and deviations show the model error the likelihood with process noise then accounts for.

``--laws``: the paper's method with the gradient and the least-squares law at ε = 0.05 and the
shipped ε, on DATA_EMPS and on the record cut at sample 9000 (the test's record that begins in
motion), and the error filter F(s) of the observer at each ε: the figures of
docs/real-data-emps.md on the choice of law and ε.

``--fits``: ``mle`` from samples 0, 3000 and 9000 on: the final fit's mean square and Gaussian
core of the normalised innovations against their bounds, the share beyond ±3, q, and the first
q searched with its window — the figures of docs/real-data-emps.md on fit consistency and q.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import signal

#: IDIM-LS filter: 4th-order Butterworth, cut-off 30 Hz (well above the trajectory's content,
#: well below the 500 Hz Nyquist frequency), run forward and backward.
IDIM_CUTOFF_HZ = 30.0


def idim_ls(t: np.ndarray, tau: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The benchmark's inverse-model least squares (its section 3.4), for the comparison."""
    dt = float(np.median(np.diff(t)))
    b, a = signal.butter(4, IDIM_CUTOFF_HZ * 2 * dt, "low")
    qf = signal.filtfilt(b, a, q)
    qd = np.gradient(qf, dt)
    qdd = np.gradient(qd, dt)
    X = np.column_stack([qdd, qd, np.sign(qd), np.ones_like(qd)])[100:-100]
    theta, *_ = np.linalg.lstsq(X, signal.filtfilt(b, a, tau)[100:-100], rcond=None)
    return theta


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--laws", action="store_true",
                    help="only the paper's method by law and ε (full and cut record)")
    ap.add_argument("--fits", action="store_true",
                    help="only mle's fits on the full and the cut records: consistency, q")
    args = ap.parse_args(argv)
    if args.laws:
        return laws_and_eps()
    if args.fits:
        return final_fits()
    import tempfile

    from thetahat.models import emps
    from thetahat.models.emps_report import METHODS, report

    rec = emps.load()
    duration = float(rec.t[-1] - rec.t[0])
    t0 = time.perf_counter()
    th_ls = idim_ls(rec.t, rec.u[:, 0], rec.y[:, 0])
    ls_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        report(out=tmp, verbose=False)                  # warm-up: every kernel cached
        done = report(out=tmp, verbose=False)
    pub = emps.PUBLISHED.value
    out = {"idim_ls": {"seconds": ls_s, "theta": th_ls.tolist()}, "record_seconds": duration}
    print(f"EMPS: {rec.t.size} samples, {duration:.2f} s of record; IDIM-LS {ls_s:.3g} s, "
          f"θ off by {np.round(100 * (th_ls - pub) / np.abs(pub), 2).tolist()} %")
    for run in done.runs:
        dev = 100 * (run.theta_hat[-1] - pub) / np.abs(pub)
        print(f"  {run.method:<8} {run.seconds:6.2f} s   {run.seconds / duration:6.3f}× real time "
              f"  {run.seconds / ls_s:7.0f}× IDIM-LS   θ̂ off by {np.round(dev, 2).tolist()} %")
        out[run.method] = {"seconds": run.seconds, "real_time_factor": run.seconds / duration,
                           "vs_idim_ls": run.seconds / ls_s,
                           "theta_hat": run.theta_hat[-1].tolist()}
    assert tuple(r.method for r in done.runs) == METHODS
    from thetahat.modelfile import load_model
    from thetahat.models.emps_report import MODEL_FILE
    spec = load_model(MODEL_FILE)
    out["ekf"] = joint_ekf(spec, rec, ls_s, duration)
    out["output_error"] = output_error_fit(spec, rec)
    return out


def joint_ekf(spec, rec, ls_s: float, duration: float) -> dict:
    """``thetahat.JointEKF(system=…).run`` on the record, as a user calls it (defaults: the
    model taken as exact, q_x = 0; σ from the record): its θ̂ or the instant it diverges."""
    import thetahat
    from thetahat.errors import NonFiniteError
    from thetahat.models import emps
    ekf = thetahat.JointEKF(system=spec.system)
    t0 = time.perf_counter()
    try:
        th = np.asarray(ekf.run(rec.t, rec.u, rec.y,
                                state0=ekf.init(theta_hat0=spec.estimator.theta_hat0)
                                ).theta_hat)[-1]
    except NonFiniteError as exc:
        print(f"  {'ekf':<8} diverged: {exc}")
        return {"diverged": str(exc)}
    s = time.perf_counter() - t0
    dev = 100 * (th - emps.PUBLISHED.value) / np.abs(emps.PUBLISHED.value)
    print(f"  {'ekf':<8} {s:6.2f} s   {s / duration:6.3f}× real time   {s / ls_s:7.0f}× IDIM-LS"
          f"   θ̂ off by {np.round(dev, 2).tolist()} %")
    return {"seconds": s, "real_time_factor": s / duration, "theta_hat": th.tolist()}


def output_error_fit(spec, rec) -> dict:
    """The MAP fit of all the record with the model taken as exact (no process noise)."""
    from thetahat.estimation.statistical.common import theta_prior_sd, x_prior_sd
    from thetahat.estimation.statistical.map_fit import fit_map
    from thetahat.estimation.statistical.noise_level import estimate_noise_std
    from thetahat.models import emps
    q0 = np.concatenate([spec.estimator.x_hat0, spec.estimator.theta_hat0])
    sd = np.concatenate([x_prior_sd(spec.estimator.x_hat0), theta_prior_sd(spec.system)])
    fit = fit_map(spec.system, rec.t, rec.u, rec.y, k0=0, k1=rec.t.size, q_start=q0,
                  q_prior=q0, prior_info=np.diag(1.0 / sd ** 2),
                  noise_std=estimate_noise_std(rec.y), max_iter=40)
    pub = emps.PUBLISHED.value
    dev = 100 * (fit.theta - pub) / np.abs(pub)
    print(f"  output error (model taken as exact): cost per measurement {fit.cost:.3g} "
          f"(consistent: {fit.consistent}), θ̂ off by {np.round(dev, 2).tolist()} %")
    return {"cost": fit.cost, "consistent": fit.consistent, "theta": fit.theta.tolist()}


def laws_and_eps(cut: int = 9000) -> dict:
    """The paper's method by update law and ε, on the full and the cut record."""
    import re
    import warnings

    from thetahat.io.datafile import read_data
    from thetahat.errors import ThetahatWarning
    from thetahat.estimation.observer.laws.least_squares import error_filter
    from thetahat.modelfile import build_estimator, loads_model, run_estimator
    from thetahat.models import emps
    from thetahat.models.emps_report import MODEL_FILE
    text = MODEL_FILE.read_text()
    shipped = loads_model(text).estimator.eps
    data = read_data(MODEL_FILE.parent / "data" / "emps" / "DATA_EMPS.mat",
                     loads_model(text).layout)
    pub = emps.PUBLISHED.value
    out = {}
    for law in ("gradient", "least_squares"):
        for eps in (0.05, shipped):
            spec = loads_model(re.sub(r'\nlaw = "[a-z_]+"', f'\nlaw = "{law}"',
                                      re.sub(r"\neps = [0-9.]+", f"\neps = {eps!r}", text)))
            obs = build_estimator(spec, method="paper", Gamma=np.eye(4)).observer
            poles = np.sort(np.linalg.eigvals(
                error_filter(spec.system, obs.K_x, obs.K_phi).L).real)
            for k0 in (0, cut):
                t, u, y = data.t[k0:] - data.t[k0], data.u[k0:], data.y[k0:]
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", ThetahatWarning)
                    th = run_estimator(spec, t, u, y, method="paper",
                                       diagnose=False).theta_hat[-1]
                dev = np.round(100 * (th[:3] - pub[:3]) / pub[:3], 1).tolist()
                print(f"  {law:<14} ε = {eps:<6g} poles {np.round(poles, 1).tolist()}  "
                      f"{'full' if k0 == 0 else f'from {k0}':>10}: M, Fv, Fc off by {dev} %, "
                      f"offset {th[3] - pub[3]:+.2f} N")
                out[f"{law} {eps:g} {k0}"] = th.tolist()
    return out



def final_fits(cuts: tuple[int, ...] = (0, 3000, 9000)) -> dict:
    """mle on DATA_EMPS from each cut on: the final fit's consistency (the mean square and the
    Gaussian core of its innovations against their bounds, FitResult.consistent) and q, the
    first q searched and the window it was searched on, θ̂, the fit's RK4 sub-steps and the
    Gauss–Newton step it still had to go (FitResult.step_se)."""
    import warnings

    from thetahat.io.datafile import read_data
    from thetahat.errors import ThetahatWarning
    from thetahat.estimation.statistical.map_fit import STEP_TOL
    from thetahat.estimation.statistical.noise_level import MAD_VARIANCE_SD
    from thetahat.modelfile import load_model, run_estimator
    from thetahat.models import emps
    from thetahat.models.emps_report import MODEL_FILE
    spec = load_model(MODEL_FILE)
    data = read_data(MODEL_FILE.parent / "data" / "emps" / "DATA_EMPS.mat", spec.layout)
    pub = emps.PUBLISHED.value
    out = {}
    for k0 in cuts:
        t, u, y = data.t[k0:] - data.t[k0], data.u[k0:], data.y[k0:]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ThetahatWarning)
            res = run_estimator(spec, t, u, y, method="mle", diagnose=False)
        fits = res.diagnostics.fits
        f = fits[-1]
        first = next(g for g in fits if g.process_noise > 0)
        root_n = np.sqrt(f.n_meas)
        th = res.theta_hat[-1]
        dev = np.round(100 * (th[:3] - pub[:3]) / pub[:3], 2).tolist()
        print(f"  {'full' if k0 == 0 else f'from {k0}':>10}: mean ν² {f.cost:.3f} "
              f"(≤ {1 + 6 * np.sqrt(2) / root_n:.3f}), core {f.core_cost:.3f} "
              f"(≤ {1 + 6 * MAD_VARIANCE_SD / root_n:.3f}), beyond ±3 {100 * f.burst_fraction:.2f} %"
              f", consistent {f.consistent}; q {f.process_noise:.3g}, first q {first.process_noise:.3g}"
              f" on {first.q_window} samples ({first.process_noise / f.process_noise:.0f}×); "
              f"M, Fv, Fc off by {dev} %, offset {th[3] - pub[3]:+.2f} N; "
              f"{f.substeps} RK4 sub-steps a sample, the step still to go "
              f"{f.step_se:.2f} sd (converged: < {STEP_TOL})")
        out[k0] = {"cost": f.cost, "core": f.core_cost, "burst": f.burst_fraction,
                   "q": f.process_noise, "first_q": first.process_noise, "theta": th.tolist(),
                   "substeps": f.substeps, "step_se": f.step_se}
    return out


if __name__ == "__main__":
    main()
