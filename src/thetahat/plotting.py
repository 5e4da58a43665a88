"""Figures like the paper's Fig. 1 (optional extra: needs matplotlib, imported lazily)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .errors import MissingExtraError
from .safe_io import atomic_path


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
        with atomic_path(path) as tmp:                   # never a half-written figure
            fig.savefig(tmp, dpi=120)
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
        From :func:`thetahat.studies.sweep.eps_sweep`.
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
        with atomic_path(path) as tmp:                   # never a half-written figure
            fig.savefig(tmp, dpi=120)
    if show:  # pragma: no cover - interactive
        plt.show()
    return fig


def _names(names: Sequence[str] | None, prefix: str, count: int) -> list[str]:
    if names is None:
        return [f"{prefix}{i + 1}" for i in range(count)]
    return list(names)


def plot_result(result: Any, system: Any, path: str | Path | None = None, *,
                y: ArrayLike | None = None, theta: ArrayLike | None = None,
                output_names: Sequence[str] | None = None,
                parameter_names: Sequence[str] | None = None,
                band: float = 0.01, show: bool = False) -> Any:
    """A figure of any model's estimates: outputs vs their estimates, φ̂, and θ̂ in Θ.

    One row of panels per output (y and C x̂, and C x̂₂ of the second observer when there is
    one), per perturbation channel (φ̂_i) and per parameter (θ̂_i with Θ's bounds and a ±band
    around the true θ_i, or around θ̂_i(t_end) when θ is not given).

    Parameters
    ----------
    result : EstimateResult
        From any estimator's ``run`` (:class:`~thetahat.estimation.protocol.Estimator`) or
        ``thetahat estimate``.
    system : PerturbedLinearSystem or ModelSpec
        C and Θ (a model file's spec also supplies the names).
    path : str or Path, optional
        Where to save (PNG, PDF, SVG by suffix); the folder is created.
    y : array_like, shape (N, r), optional
        The measured outputs, drawn under the estimates.
    theta : array_like, shape (p,), optional
        The true θ (simulations): the band is drawn around it.
    output_names, parameter_names : sequence of str, optional
        Labels (default: from a ModelSpec, else y1…, θ1…).
    band : float
        Relative half-width of the band around θ (default 1 %, the accuracy the examples aim
        for).
    show : bool
        Show the window (interactive use).

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> from thetahat.models import two_inertia
    >>> from thetahat.plotting import plot_result
    >>> tr = two_inertia.simulate(seed=0, t_end=0.3)
    >>> res = two_inertia.observer().run(tr.t, tr.u, tr.y)
    >>> fig = plot_result(res, two_inertia.system(), y=tr.y, theta=tr.theta)
    >>> len(fig.axes)     # 2 outputs, 2 channels, 2 parameters
    6
    """
    plt = _pyplot(show)
    sys_ = getattr(system, "system", system)
    if output_names is None and hasattr(system, "output_names"):
        output_names = system.output_names
    if parameter_names is None and hasattr(system, "parameter_names"):
        parameter_names = system.parameter_names
    t = np.asarray(result.t, float)
    yhat = np.asarray(result.x_hat, float) @ sys_.C.T
    y2 = (None if result.x_hat_refined is None
          else np.asarray(result.x_hat_refined, float) @ sys_.C.T)
    r, k, p = yhat.shape[1], result.phi_hat.shape[1], result.theta_hat.shape[1]
    onames = _names(output_names, "y", r)
    pnames = _names(parameter_names, "θ", p)
    fig, ax = plt.subplots(r + k + p, 1, figsize=(8, 1.9 * (r + k + p) + 0.6), sharex=True)
    ax = np.atleast_1d(ax)
    for i in range(r):
        if y is not None:
            ax[i].plot(t, np.asarray(y, float).reshape(t.size, r)[:, i], color="0.6", lw=0.6,
                       label=f"{onames[i]} (measured)")
        ax[i].plot(t, yhat[:, i], color="tab:blue", lw=1.0, label="C x̂")
        if y2 is not None:
            ax[i].plot(t, y2[:, i], "--", color="tab:green", lw=1.0, label="C x̂₂")
        ax[i].set_ylabel(onames[i])
    for j in range(k):
        ax[r + j].plot(t, np.asarray(result.phi_hat, float)[:, j], color="tab:purple", lw=1.0,
                       label=f"φ̂{j + 1}")
        ax[r + j].set_ylabel(f"φ̂{j + 1}")
    box = sys_.parameter_set
    lower, upper = getattr(box, "lower", None), getattr(box, "upper", None)
    th_hat = np.asarray(result.theta_hat, float)
    for i in range(p):
        panel = ax[r + k + i]
        centre = float(np.ravel(theta)[i]) if theta is not None else float(th_hat[-1, i])
        half = band * max(abs(centre), 1e-12)
        panel.axhspan(centre - half, centre + half, color="tab:orange", alpha=0.25,
                      label=f"±{band:.0%} of {'θ' if theta is not None else 'θ̂(end)'}")
        if theta is not None:
            panel.axhline(centre, color="k", lw=0.8, label="true")
        if lower is not None and upper is not None:       # a Box Θ has both bounds
            panel.axhline(float(np.ravel(lower)[i]), color="tab:red", ls=":", lw=1.0,
                          label="Θ")
            panel.axhline(float(np.ravel(upper)[i]), color="tab:red", ls=":", lw=1.0)
        panel.plot(t, th_hat[:, i], color="tab:blue", lw=1.2, label="θ̂")
        panel.set_ylabel(pnames[i])
    for panel in ax:
        panel.legend(loc="upper right", fontsize=7)
        panel.grid(alpha=0.3)
    ax[-1].set_xlabel("t [s]")
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:                   # never a half-written figure
            fig.savefig(tmp, dpi=110)
    if show:  # pragma: no cover - interactive
        plt.show()
    return fig
