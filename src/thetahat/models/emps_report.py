"""The EMPS benchmark end to end: estimate with every method, validate, compare, draw.

Used by ``thetahat demo emps``. Reads ``examples/emps.toml`` and the record
``examples/data/emps/DATA_EMPS.mat`` through the normal path (:func:`thetahat.io.datafile.read_data`
with the file's ``[data]`` table, :func:`thetahat.modelfile.run_estimator`), and for each method
writes the estimates and prints its summary; then one table of θ̂ per method beside the
published IDIM-LS values, the benchmark's closed-loop validation (eq. 11,
:func:`thetahat.models.emps.validate`) of each θ̂ and of the published θ, and — with matplotlib
— the figure ``emps.png``: θ̂(t) per method against the published values ± 3σ, and the measured
against the simulated position and force.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..safe_io import atomic_path, check_writable
from . import emps

__all__ = ["MODEL_FILE", "METHODS", "EmpsRun", "EmpsReport", "report"]

#: The shipped model file of the benchmark.
MODEL_FILE = emps.DATA_FILE.parents[2] / "emps.toml"
#: The methods the demo runs, in its table's order.
METHODS = ("paper", "guarded", "mle")


@dataclass(frozen=True, slots=True, repr=False)
class EmpsRun:
    """One method on DATA_EMPS.

    Attributes
    ----------
    method : str
    t : ndarray (N,)
    theta_hat : ndarray (N, 4)
        θ̂ over the record.
    validation : EmpsValidation
        The closed loop simulated with the final θ̂.
    warnings : tuple of str
        What the run warned of.
    seconds : float
        Wall time of the estimation.
    estimates : Path
        The CSV written.
    """

    method: str
    t: NDArray[np.float64]
    theta_hat: NDArray[np.float64]
    validation: emps.EmpsValidation
    warnings: tuple[str, ...]
    seconds: float
    estimates: Path

    def __repr__(self) -> str:
        return (f"EmpsRun(method={self.method!r}, theta_hat={self.theta_hat[-1].tolist()}, "
                f"seconds={self.seconds:.3g})")


@dataclass(frozen=True, slots=True, repr=False)
class EmpsReport:
    """What ``thetahat demo emps`` computed.

    Attributes
    ----------
    runs : tuple of EmpsRun
    published : EmpsValidation
        The closed loop simulated with the published IDIM-LS θ.
    figure : Path or None
        The figure written (None without matplotlib).
    """

    runs: tuple[EmpsRun, ...]
    published: emps.EmpsValidation
    figure: Path | None

    def table(self) -> str:
        """θ̂ per method beside the published values (deviation in %, and in σ of the
        published table), then the eq.-(11) errors of each and of the published θ.

        Returns
        -------
        str
        """
        pub = emps.PUBLISHED
        head = f"{'':<10}" + "".join(f"{r.method:>18}" for r in self.runs) + f"{'published':>18}"
        lines = [head]
        for i, name in enumerate(pub.names):
            cells = []
            for r in self.runs:
                est = r.theta_hat[-1, i]
                cells.append(f"{est:9.5g} ({100 * (est - pub.value[i]) / abs(pub.value[i]):+5.1f}%)")
            lines.append(f"{name:<10}" + "".join(f"{c:>18}" for c in cells)
                         + f"{pub.value[i]:>11.5g} ± {pub.sigma[i]:<4.2g}")
        lines.append("")
        lines.append(f"{'eq. (11)':<10}" + "".join(f"{r.method:>18}" for r in self.runs)
                     + f"{'published θ':>18}{'published':>12}")
        for key in ("position", "velocity", "force"):
            lines.append(f"{key:<10}" + "".join(f"{getattr(r.validation, key):>16.4g} %"
                                                 for r in self.runs)
                         + f"{getattr(self.published, key):>16.4g} %"
                         + f"{emps.PUBLISHED_VALIDATION[key]:>10.4g} %")
        lines.append(f"{'seconds':<10}" + "".join(f"{r.seconds:>18.3g}" for r in self.runs))
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"EmpsReport(runs={list(self.runs)!r})"


def _figure(runs: Sequence[EmpsRun], record: emps.EmpsRecord, path: Path) -> Path | None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    pub = emps.PUBLISHED
    fig, axes = plt.subplots(3, 2, figsize=(11, 9), constrained_layout=True)
    for i, ax in enumerate(axes[:2].ravel()):
        for r in runs:
            ax.plot(r.t, r.theta_hat[:, i], lw=1, label=r.method)
        v, s = pub.value[i], pub.sigma[i]
        ax.axhline(v, color="k", lw=0.8, label="published")
        ax.axhspan(v - 3 * s, v + 3 * s, color="k", alpha=0.15, label="± 3σ")
        lo, hi = v - 0.25 * abs(v) - 1, v + 0.25 * abs(v) + 1
        ax.set_ylim(lo, hi)
        ax.set_title(f"{pub.names[i]}: θ̂(t)")
        ax.set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=8)
    best = runs[-1]
    ax = axes[2, 0]
    ax.plot(record.t, record.y[:, 0], "k", lw=1, label="measured")
    for r in runs:
        ax.plot(record.t, r.validation.q_sim, lw=0.8, label=f"simulated ({r.method})")
    ax.set_title("position q [m]: measured vs closed loop simulated with θ̂")
    ax.set_xlabel("t [s]")
    ax.legend(fontsize=8)
    ax = axes[2, 1]
    ax.plot(record.t, record.u[:, 0], "k", lw=0.6, label="measured")
    ax.plot(record.t, best.validation.force_sim, lw=0.6, label=f"simulated ({best.method})")
    ax.set_title("force τ [N]")
    ax.set_xlabel("t [s]")
    ax.legend(fontsize=8)
    with atomic_path(path) as tmp:                   # never a half-written figure
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def report(*, out: Path | str = "out", methods: Sequence[str] = METHODS,
           verbose: bool = True) -> EmpsReport:
    """Estimate θ on DATA_EMPS with the shipped model file by each method and validate it.

    Parameters
    ----------
    out : path
        Output folder (created); the estimates go to ``out/emps_<method>.csv``, the figure
        to ``out/emps.png``.
    methods : sequence of str
        The estimators (names of :data:`thetahat.methods.METHODS`), in the table's order.
    verbose : bool
        Print each summary and the tables.

    Returns
    -------
    EmpsReport

    Raises
    ------
    ModelFileError
        The model file or the record is missing (an installed package without the
        repository's ``examples/``), or an output cannot be written (checked before any
        work).
    """
    from ..io.datafile import read_data, write_estimates
    from ..modelfile import load_model, run_estimator
    from ..studies.metrics import estimate_summary

    for name in [f"emps_{method}.csv" for method in methods] + ["emps.png"]:   # before work
        check_writable(Path(out) / name)
    spec = load_model(MODEL_FILE)
    data = read_data(emps.DATA_FILE, spec.layout)
    record = emps.load()
    Path(out).mkdir(parents=True, exist_ok=True)
    runs = []
    for method in methods:
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = run_estimator(spec, data.t, data.u, data.y, method=method)
        seconds = time.perf_counter() - t0
        path = Path(out) / f"emps_{method}.csv"
        write_estimates(path, result, spec.layout)
        notes = tuple(f"{w.category.__name__}: {w.message}" for w in caught)
        theta_hat = np.array(result.theta_hat, dtype=np.float64)
        runs.append(EmpsRun(method=method, t=np.asarray(result.t), theta_hat=theta_hat,
                            validation=emps.validate(theta_hat[-1], record),
                            warnings=notes, seconds=seconds, estimates=path))
        if verbose:
            print(f"EMPS (Janot, Gautier & Brunot 2019): {data.t.size} samples, "
                  f"{MODEL_FILE.name}, method {method}; wrote {path}")
            print(estimate_summary(result, warnings=notes))
            print()
    figure = _figure(runs, record, Path(out) / "emps.png")
    done = EmpsReport(runs=tuple(runs), published=emps.validate(emps.PUBLISHED.value, record),
                      figure=figure)
    if verbose:
        print(done.table())
        if figure is not None:
            print(f"wrote {figure}")
    return done
