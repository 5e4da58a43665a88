"""The paper's example end to end (Sec. VIII): structure, design, estimation, Fig. 1, summary.

Used by ``examples/lugre_demo.py`` (``make demo``) and by ``thetahat demo lugre``.

The default scenario is ours (the paper gives none): 20 s, u(t) = 0.7 sin(2π·0.5t)
+ 0.25 sin(2π·1.3t) N m, ω(0) = η(0) = 0, y sampled at 1 kHz with noise σ = 0.02 rad/s,
θ̂(0) = 0.5, true α0 = 0.28.
"""

from __future__ import annotations

from typing import Any

import json
import time
import warnings
from pathlib import Path

import numpy as np

from . import lugre
from ..design.design_system import apply_design
from ..design.gains import extended_system
from ..errors import IllConditionedWarning
from ..structure.assumptions import check_assumption_1
from ..structure.scb import scb
from ..safe_io import atomic_path, check_writable, write_text
from ..studies.metrics import rmse, time_to_within


def structure_report(params: lugre.LuGreParameters) -> None:
    for s1 in (params.sigma1, 0.0):
        lin = lugre.linear_part(params, sigma1=s1)
        print(f"--- σ1 = {s1}: " + str(check_assumption_1(lin.A, lin.E, lin.C)).replace(
            "\n", "\n    "))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedWarning)
            print(f"    SCB of (4): {scb(*extended_system(lin.A, lin.E, lin.C))}")


#: The files :func:`report` writes into its folder.
OUTPUTS = ("lugre.json", "lugre.png", "lugre_data.csv")


def report(*, out: Path | str = "out", eps: float = 1.0, seed: int = 0, show: bool = False,
           verbose: bool = True) -> dict[str, Any]:
    """Run the example; write ``out/lugre.png``, ``out/lugre.json`` and the data
    ``out/lugre_data.csv`` (columns t, u, y); return the summary.

    Parameters
    ----------
    out : path
        Output folder (created).
    eps : float
        ε of the first observer.
    seed : int
        Seed of the measurement noise.
    show : bool
        Open the figure window.
    verbose : bool
        Print the structural report and the summary table.

    Returns
    -------
    dict
        The content of ``lugre.json``: ``K1``, ``K2``, ``theta_hat_final``, ``t_5pct``,
        ``t_1pct``, ``rmse`` (ω̂, η̂ of both observers, over all samples and over t ≥ 10 s),
        ``wall_s``.

    Raises
    ------
    ModelFileError
        An output (:data:`OUTPUTS`) cannot be written (checked before any work).
    """
    say = print if verbose else (lambda *a, **k: None)
    out = Path(out)
    for name in OUTPUTS:                                              # before any work
        check_writable(out / name)
    params = lugre.LuGreParameters()
    if verbose:
        structure_report(params)
    d1, d2 = lugre.designs(eps)
    lin = lugre.linear_part(params)
    rep = apply_design(d1, lin.A, lin.E, lin.C)
    say(f"K1 (first observer, ε = {eps:g}) = {np.round(d1.K.ravel(), 5).tolist()}")
    say(f"K2 (second observer, ε = 1)      = {np.round(d2.K.ravel(), 5).tolist()}")
    say(f"true error dynamics with K1: stable = {rep.stable}, "
          f"max Re λ = {rep.eig_true.real.max():.3f}")

    t0 = time.perf_counter()
    data = lugre.simulate(seed=seed)
    t_sim = time.perf_counter() - t0
    obs = lugre.observer(eps)
    t0 = time.perf_counter()
    res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=[lugre.Scenario().theta_hat0]))
    t_obs = time.perf_counter() - t0

    alpha0 = float(data.theta[0])
    half = data.t.size // 2
    x2 = np.asarray(res.x_hat_refined, dtype=np.float64)      # the second observer's x̂₂
    summary: dict[str, Any] = {
        "K1": d1.K.ravel().tolist(),
        "K2": d2.K.ravel().tolist(),
        "eps": eps,
        "seed": seed,
        "alpha0": alpha0,
        "theta_hat_final": float(res.theta_hat[-1, 0]),
        "t_5pct": time_to_within(data.t, res.theta_hat, data.theta, 0.05),
        "t_1pct": time_to_within(data.t, res.theta_hat, data.theta, 0.01),
        "rmse": {
            "window": "all samples; *_second_half: t >= 10 s, after θ̂ has converged",
            "first_omega": float(rmse(res.x_hat[:, 0], data.x[:, 0])[0]),
            "first_eta": float(rmse(res.x_hat[:, 1], data.x[:, 1])[0]),
            "second_omega": float(rmse(x2[:, 0], data.x[:, 0])[0]),
            "second_eta": float(rmse(x2[:, 1], data.x[:, 1])[0]),
            "first_omega_second_half": float(rmse(res.x_hat[:, 0], data.x[:, 0], start=half)[0]),
            "first_eta_second_half": float(rmse(res.x_hat[:, 1], data.x[:, 1], start=half)[0]),
            "second_omega_second_half": float(
                rmse(x2[:, 0], data.x[:, 0], start=half)[0]),
            "second_eta_second_half": float(
                rmse(x2[:, 1], data.x[:, 1], start=half)[0]),
            "measurement_noise": float(rmse(data.y[:, 0], data.x[:, 0])[0]),
        },
        "wall_s": {"simulate": t_sim, "observer": t_obs,
                   "observer_us_per_step": 1e6 * t_obs / data.t.size},
    }
    write_text(out / "lugre.json", json.dumps(summary, indent=2))         # atomic
    # the record the observer ran on, in the layout `thetahat estimate` and the generated C
    # harness read (thetahat codegen examples/lugre.toml --dt 1e-3 ...)
    with atomic_path(out / "lugre_data.csv") as tmp:
        np.savetxt(tmp, np.c_[data.t, data.u, data.y], delimiter=",", header="t,u,y",
                   comments="", fmt="%.17g")
    from ..plotting import figure_1
    with atomic_path(out / "lugre.png") as tmp:
        figure_1(data.t, data.y, data.x, x2, data.theta, res.theta_hat,
                 x_hat_first=res.x_hat, path=tmp, show=show)

    r = summary["rmse"]
    say()
    say(f"{'':28s}{'first observer':>16s}{'second observer':>17s}")
    say(f"{'ω̂ RMSE, all / t ≥ 10 s':28s}{r['first_omega']:8.4f} /{r['first_omega_second_half']:7.4f}"
          f"{r['second_omega']:9.4f} /{r['second_omega_second_half']:7.4f}  rad/s")
    say(f"{'η̂ RMSE, all / t ≥ 10 s':28s}{r['first_eta']:8.1e} /{r['first_eta_second_half']:7.1e}"
          f"{r['second_eta']:9.1e} /{r['second_eta_second_half']:7.1e}  rad")
    say(f"θ̂(20 s) = {summary['theta_hat_final']:.5f} (α0 = {alpha0}), within 5 % after "
          f"{summary['t_5pct']:.2f} s, within 1 % after {summary['t_1pct']:.2f} s")
    say(f"wall time: simulate {t_sim:.2f} s, observer {t_obs:.2f} s "
          f"({summary['wall_s']['observer_us_per_step']:.0f} µs/step)")
    say(f"wrote {out / 'lugre.png'}, {out / 'lugre.json'} and {out / 'lugre_data.csv'}")
    return summary
