"""Figures like the paper's Fig. 1 (optional extra: needs matplotlib, imported lazily)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .errors import MissingExtraError


def _pyplot(show: bool) -> Any:
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - optional extra
        raise MissingExtraError("plotting needs matplotlib: pip install 'thetahat[plot]'") from exc
    if not show:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def figure_1(t: ArrayLike, y: ArrayLike, x: ArrayLike, x_hat: ArrayLike, theta: ArrayLike,
             theta_hat: ArrayLike, *, state_labels: Sequence[str] = ("ω [rad/s]", "η [rad]"),
             theta_label: str = "θ [N m]", x_hat_first: ArrayLike | None = None,
             path: str | Path | None = None, show: bool = False) -> Any:
    """The four panels of the paper's Fig. 1.

    From the top: the first state and its noisy measurement y; the first state and its
    estimate; the second state and its estimate; θ and θ̂. With ``x_hat_first`` the first
    observer's estimates are drawn too (thin), next to ``x_hat`` (e.g. the second observer's).

    Parameters
    ----------
    t : array_like, shape (N,)
    y : array_like, shape (N,) or (N, 1)
    x, x_hat : array_like, shape (N, 2)
        True states and the estimates to show (the paper: the second observer's).
    theta : array_like, shape (1,) or scalar
        The true constant parameter.
    theta_hat : array_like, shape (N,) or (N, 1)
    state_labels, theta_label : str
        Axis labels.
    x_hat_first : array_like, shape (N, 2), optional
        The first observer's estimates, drawn thin for comparison.
    path : str or Path, optional
        Where to save (PNG by suffix); the parent folder is created.
    show : bool
        Show the window (interactive use).

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot(show)
    t = np.asarray(t, float)
    x, xh = np.asarray(x, float), np.asarray(x_hat, float)
    fig, ax = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    ax[0].plot(t, x[:, 0], "k", lw=1.0, label=state_labels[0].split()[0])
    ax[0].plot(t, np.asarray(y, float).ravel(), color="tab:red", lw=0.4, alpha=0.6,
               label="y (noisy measurement)")
    for i, panel in ((0, ax[1]), (1, ax[2])):
        panel.plot(t, x[:, i], "k", lw=1.0, label="true")
        if x_hat_first is not None:
            panel.plot(t, np.asarray(x_hat_first, float)[:, i], color="tab:orange", lw=0.6,
                       alpha=0.7, label="first observer")
        panel.plot(t, xh[:, i], "--", color="tab:blue", lw=1.0, label="estimate")
    ax[3].plot(t, np.full_like(t, float(np.ravel(theta)[0])), "k", lw=1.0, label="true")
    ax[3].plot(t, np.asarray(theta_hat, float).ravel(), "--", color="tab:blue", lw=1.0,
               label="estimate")
    for panel, lab in zip(ax, (state_labels[0], state_labels[0], state_labels[1], theta_label)):
        panel.set_ylabel(lab)
        panel.legend(loc="upper right", fontsize=8)
        panel.grid(alpha=0.3)
    ax[-1].set_xlabel("t [s]")
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    if show:  # pragma: no cover - interactive
        plt.show()
    return fig


def plot_sweep(result: Any, path: str | Path | None = None, show: bool = False, *,
               state_labels: Sequence[str] | None = None) -> Any:
    """Metrics of an ε sweep against ε (log scale, ε decreasing to the right), divergences marked.

    Four panels: the settling time of θ̂ to 1 %; max |θ̂ − θ| and the θ RMSE over the second
    half of the record; the state RMSE of the first observer (solid) and of the second
    (dashed), per component. Dots are single runs, lines join the medians over the stable
    runs, and a red cross on the axis plus a shaded band mark every ε at which some run
    diverged (with the count of diverged runs).

    Parameters
    ----------
    result : SweepResult
        From :func:`thetahat.simulation.sweep.eps_sweep`.
    path : str or Path, optional
        Where to save (PNG by suffix); the parent folder is created.
    show : bool
        Show the window (interactive use).
    state_labels : sequence of str, optional
        Names of the state components (default x1, x2, ...).

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot(show)
    eps = np.asarray(result.eps, float)
    rows = result.rows
    bad = result.diverged
    n = result.x_rmse.shape[-1]
    labels = list(state_labels) if state_labels is not None else [f"x{i + 1}" for i in range(n)]
    fig, ax = plt.subplots(4, 1, figsize=(7, 10), sharex=True)

    def runs(panel: Any, values: np.ndarray, color: str, marker: str = "o") -> None:
        for i, e in enumerate(eps):
            ok = ~bad[i] & np.isfinite(values[i])
            panel.plot(np.full(int(ok.sum()), e), values[i][ok], marker, color=color, ms=3,
                       alpha=0.5, ls="none")

    runs(ax[0], result.t_1pct, "tab:blue")
    ax[0].plot(eps, [r.t_1pct_median for r in rows], "-", color="tab:blue", label="median")
    ax[0].set_ylabel("t to 1 % [s]")
    runs(ax[1], result.theta_max_error, "tab:blue")
    ax[1].plot(eps, [r.theta_max_error_median for r in rows], "-", color="tab:blue",
               label="max |θ̂ − θ|")
    ax[1].set_ylabel("max |θ̂ − θ|\n(2nd half)")
    runs(ax[2], result.theta_rmse, "tab:green")
    ax[2].plot(eps, [r.theta_rmse_median for r in rows], "-", color="tab:green",
               label="θ RMSE")
    ax[2].set_ylabel("θ RMSE\n(2nd half)")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i in range(n):
        c = colors[i % len(colors)]
        runs(ax[3], result.x_rmse[..., i], c)
        ax[3].plot(eps, [r.x_rmse_median[i] for r in rows], "-", color=c,
                   label=f"{labels[i]} (first)")
        if result.x_rmse_refined is not None:
            runs(ax[3], result.x_rmse_refined[..., i], c, marker="s")
            ax[3].plot(eps, [r.x_rmse_refined_median[i] for r in rows], "--", color=c,
                       label=f"{labels[i]} (second)")
    ax[3].set_ylabel("state RMSE\n(2nd half)")
    for panel in ax:
        panel.set_xscale("log")
        panel.grid(alpha=0.3, which="both")
        if panel is not ax[0]:
            panel.set_yscale("log")
        labelled = panel is not ax[0]
        for i, e in enumerate(eps):
            if bad[i].any():
                panel.axvspan(e / 1.08, e * 1.08, color="tab:red", alpha=0.15, lw=0)
                panel.plot([e], [0.97], "x", color="tab:red", ms=8, mew=2, ls="none",
                           transform=panel.get_xaxis_transform(), clip_on=False,
                           label=None if labelled else "diverged (count below)")
                labelled = True
        panel.legend(loc="best", fontsize=8)
    for i, e in enumerate(eps):
        if bad[i].any():
            ax[0].annotate(f"{int(bad[i].sum())}/{bad.shape[1]}", (e, 0.88),
                           xycoords=ax[0].get_xaxis_transform(), ha="center", va="top",
                           fontsize=7, color="tab:red")
    ax[0].invert_xaxis()                       # the tuning of Sec. VII goes from ε = 1 down
    ax[-1].set_xlabel("ε (decreasing →)")
    ax[0].set_title(result.verdict(), fontsize=9)
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    if show:  # pragma: no cover - interactive
        plt.show()
    return fig
