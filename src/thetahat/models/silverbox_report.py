"""The Silverbox benchmark end to end: estimate on the training split, validate on the test splits.

Used by ``thetahat demo silverbox``. Reads ``examples/silverbox.toml`` and the record
``examples/data/silverbox/SNLS80mV.mat`` through the normal path (the file's ``[data]`` table:
V1 → u, V2 − y₀ → y, t from the sample rate, and ``samples = "train"``;
:func:`thetahat.modelfile.run_estimator`), runs each method on the training split, and scores
every θ̂ by the benchmark's protocol (:func:`thetahat.models.silverbox.validate`: free-run
simulations of the test splits from x(0) fitted on their first 50 samples). Beside them: the
output-error fit of the same model under each input reconstruction
(:func:`thetahat.studies.validation.fit_output_error`, a converged simulator), the reference
an estimator of this model can at best reach, and the published figures of
:data:`thetahat.models.silverbox.LITERATURE`. With matplotlib, the figure ``silverbox.png``:
the test responses and each method's simulation error.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..io.record import DataRecord
from ..methods import ESTIMATION_METHODS
from ..modelfile import ModelSpec
from ..safe_io import atomic_path, check_writable
from ..spec import Hold
from ..studies.validation import FreeRunValidation, OutputErrorFit
from . import silverbox

__all__ = ["METHODS", "REFERENCE_HOLDS", "SilverboxReport", "SilverboxRun", "report"]

#: The methods the demo runs, in its table's order: every method of the registry (the joint EKF
#: for reference).
METHODS = ESTIMATION_METHODS
#: The input reconstructions of the output-error references.
REFERENCE_HOLDS = ("foh", "bandlimited")
#: The demo's hold: the one every method and the validation use (stage 2 and the observer
#: read the input linear between samples).
HOLD: Hold = "foh"

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, repr=False)
class SilverboxRun:
    """One θ̂ and its score: a method on the training split, or an output-error reference.

    Attributes
    ----------
    name : str
        The method, or "OE (hold)" for a reference.
    theta : ndarray (5,)
        θ̂ = (m, d, k1, k3, u0) at the end of the training split.
    sd : ndarray (5,)
        Its Cramér–Rao standard deviation on the training split (the trust report's; the
        output-error one for a reference; NaN when not available).
    in_theta : bool
        θ̂ lies in Θ.
    validation : FreeRunValidation
        The test splits simulated with θ̂.
    warnings : tuple of str
        What the run warned of.
    seconds : float
        Wall time of the estimation.
    """

    name: str
    theta: FloatArray
    sd: FloatArray
    in_theta: bool
    validation: FreeRunValidation
    warnings: tuple[str, ...]
    seconds: float

    def rms_mV(self, split: str) -> float:
        """The RMS simulation error on a test split, in mV."""
        return 1e3 * float(self.validation[split].rms[0])

    def __repr__(self) -> str:
        return (f"SilverboxRun({self.name!r}, theta={self.theta.tolist()}, "
                f"seconds={self.seconds:.3g})")


@dataclass(frozen=True, slots=True, repr=False)
class SilverboxReport:
    """What ``thetahat demo silverbox`` computed.

    Attributes
    ----------
    runs : tuple of SilverboxRun
        The methods, in order.
    references : tuple of SilverboxRun
        The output-error fits, one per hold of :data:`REFERENCE_HOLDS`.
    train : (int, int)
        The samples estimated from.
    hold : str
        The hold of the methods and of their validation.
    figure : Path or None
    """

    runs: tuple[SilverboxRun, ...]
    references: tuple[SilverboxRun, ...]
    train: tuple[int, int]
    hold: str
    figure: Path | None

    def reference(self, hold: str | None = None) -> SilverboxRun | None:
        """The output-error reference of a hold (default: the methods'), if it was fitted."""
        name = f"OE ({self.hold if hold is None else hold})"
        return next((r for r in self.references if r.name == name), None)

    def table(self) -> str:
        """θ̂ ± Cramér–Rao sd per method and reference, the test RMS (mV) and fit (%), the
        ratio of each RMS to the output-error reference of the same hold, the wall times, and
        the published figures.

        Returns
        -------
        str
        """
        cols = list(self.runs) + list(self.references)
        w = 23
        names = ("m", "d", "k1", "k3", "u0")
        lines = [f"trained on samples [{self.train[0]}, {self.train[1]}) "
                 f"({self.train[1] - self.train[0]} samples); methods and validation with "
                 f"hold = {self.hold!r}", "",
                 f"{'':<30}" + "".join(f"{c.name:>{w}}" for c in cols)]
        for i, name in enumerate(names):
            lines.append(f"{name:<30}" + "".join(
                f"{f'{c.theta[i]:.5g} ± {c.sd[i]:.2g}':>{w}}" for c in cols))
        lines.append(f"{'in Θ':<30}" + "".join(f"{str(c.in_theta):>{w}}" for c in cols))
        lines.append("")
        lines.append(f"{'test RMS [mV] (fit %)':<30}")
        for split in silverbox.TEST_SPLITS:
            lines.append(f"{split:<30}" + "".join(
                f"{f'{c.rms_mV(split):.4g} ({c.validation[split].fit_percent[0]:.2f})':>{w}}"
                for c in cols))
        ref = self.reference()
        if ref is not None:
            lines.append("")
            lines.append(f"ratio to the output-error fit with hold {self.hold!r}")
            for split in silverbox.TEST_SPLITS:
                lines.append(f"{split:<30}" + "".join(
                    f"{c.rms_mV(split) / ref.rms_mV(split):>{w}.3g}" for c in cols))
        lines.append(f"{'seconds':<30}" + "".join(f"{c.seconds:>{w}.3g}" for c in cols))
        lines.append("")
        lines.append("published (free-run RMS on the test split, mV):")
        for p in silverbox.LITERATURE:
            lines.append(f"  {p.model:<46} {p.kind:<10} {p.split:<28} {p.rms_mV:>6.3g}")
        lines.append(f"  source: {silverbox.LITERATURE[0].source}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"SilverboxReport(runs={list(self.runs)!r})"


#: Samples shown in the zoom of the figure's response panels (about 20 periods at 68 Hz).
ZOOM_SAMPLES = 180
#: Samples in the moving RMS of the figure's error panels.
RMS_WINDOW = 500


def _moving_rms(e: FloatArray, window: int) -> FloatArray:
    c = np.concatenate([[0.0], np.cumsum(e ** 2)])
    return np.sqrt((c[window:] - c[:-window]) / window)


def _figure(runs: Sequence[SilverboxRun], record: DataRecord, path: Path) -> Path | None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    shown = ("test_multisine", "test_arrow_full")
    fig, axes = plt.subplots(len(shown), 2, figsize=(13, 7.5), constrained_layout=True)
    every = silverbox.splits()
    for row, split in enumerate(shown):
        start, stop = every[split]
        y = record.y[start:stop, 0]
        peak = int(np.argmax(np.abs(y)))                     # the zoom: around the largest y
        lo = min(max(peak - ZOOM_SAMPLES // 2, 0), y.size - ZOOM_SAMPLES)
        zoom = slice(lo, lo + ZOOM_SAMPLES)
        t = record.t[start:stop]
        ax = axes[row, 0]
        ax.plot(t[zoom], 1e3 * y[zoom], "k.-", lw=0.8, ms=3, label="measured")
        for r in runs:
            ax.plot(t[zoom], 1e3 * r.validation[split].y_sim[zoom, 0], lw=0.9, label=r.name)
        ax.set_title(f"{split}: y [mV] around its largest sample (free run from θ̂)")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7, loc="lower left", ncol=2)
        ax = axes[row, 1]
        half = RMS_WINDOW // 2
        for r in runs:
            err = y - r.validation[split].y_sim[:, 0]
            ax.semilogy(t[half:half + err.size - RMS_WINDOW + 1],
                        1e3 * _moving_rms(err, RMS_WINDOW), lw=0.9,
                        label=f"{r.name}: {r.rms_mV(split):.3g} mV RMS")
        ax.set_title(f"{split}: simulation error y − ŷ, RMS over {RMS_WINDOW} samples [mV]")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7, loc="upper left")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def _method_run(spec: ModelSpec, train: DataRecord, record: DataRecord, method: str,
                hold: str) -> SilverboxRun:
    from ..modelfile import run_estimator, split_hold
    # the paper's observer takes the zero- and first-order holds only: with "bandlimited" it
    # runs with the linear one (its θ̂ still scored under the methods' hold)
    own = hold if method != "paper" else split_hold(hold, "guarded")[0]
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_estimator(spec, train.t, train.u, train.y, method=method, hold=own)
    seconds = time.perf_counter() - t0
    theta = np.array(result.theta_hat[-1], dtype=np.float64)
    crlb = getattr(result.trust, "crlb_sd", None)
    sd = np.full(theta.size, np.nan) if crlb is None else np.array(crlb, dtype=np.float64)
    notes = tuple(f"{w.category.__name__}: {w.message}" for w in caught)
    return SilverboxRun(name=method, theta=theta, sd=sd,
                        in_theta=bool(spec.system.require_parameter_set("Θ").contains(theta)),
                        validation=silverbox.validate(theta, record, hold=hold),
                        warnings=notes, seconds=seconds)


def _reference_run(spec: ModelSpec, train: DataRecord, record: DataRecord,
                   hold: str) -> SilverboxRun:
    from ..studies.validation import fit_output_error
    t0 = time.perf_counter()
    fit: OutputErrorFit = fit_output_error(spec.system, train.t, train.u, train.y,
                                           theta0=spec.estimator.theta_hat0, hold=hold)
    seconds = time.perf_counter() - t0
    notes = () if fit.success else (f"the fit stopped: {fit.message}",)
    return SilverboxRun(name=f"OE ({hold})", theta=np.array(fit.theta),
                        sd=np.array(fit.theta_sd),
                        in_theta=bool(spec.system.require_parameter_set("Θ").contains(fit.theta)),
                        validation=silverbox.validate(fit.theta, record, hold=hold),
                        warnings=notes, seconds=seconds)


def report(*, out: Path | str = "out", methods: Sequence[str] = METHODS,
           references: Sequence[str] = REFERENCE_HOLDS, hold: str = HOLD,
           train_samples: int | None = None, verbose: bool = True) -> SilverboxReport:
    """Estimate θ on the Silverbox training split by each method and validate it on the tests.

    Parameters
    ----------
    out : path
        Output folder (created); the figure goes to ``out/silverbox.png``.
    methods : sequence of str
        The estimators (names of :data:`thetahat.methods.METHODS`), in the table's order.
    references : sequence of str
        The holds of the output-error references (none: skip them).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        The hold the methods run with and their θ̂ are validated with (the output-error
        reference of this hold is the one the ratios are taken to); the paper's observer
        takes ``"foh"`` in place of ``"bandlimited"``.
    train_samples : int, optional
        Estimate from the first samples of the training split only (a quick look; default: all
        of it).
    verbose : bool
        Print each method's line and the tables.

    Returns
    -------
    SilverboxReport

    Raises
    ------
    ModelFileError
        The model file or the record is missing, or the figure cannot be written (checked
        before any work).
    """
    from ..io.datafile import read_data
    from ..modelfile import load_model

    figure_path = Path(out) / "silverbox.png"
    check_writable(figure_path)                                    # before any work
    spec = load_model(silverbox.MODEL_FILE)
    record = silverbox.load()
    train = read_data(silverbox.DATA_FILE, spec.layout)            # the file's samples: train
    if train_samples is not None:
        train = train.segment(0, min(int(train_samples), train.t.size))
    Path(out).mkdir(parents=True, exist_ok=True)
    runs = []
    for method in methods:
        run = _method_run(spec, train, record, method, hold)
        runs.append(run)
        if verbose:
            print(f"{method:<8} {run.seconds:7.1f} s   θ̂ = {np.array2string(run.theta, precision=5)}"
                  f"   test RMS " + ", ".join(f"{run.rms_mV(s):.3g}" for s in
                                             silverbox.TEST_SPLITS) + " mV")
            for note in run.warnings:
                print(f"         {note}")
    refs = []
    for ref_hold in references:
        refs.append(_reference_run(spec, train, record, ref_hold))
    figure = _figure(runs + refs, record, figure_path)
    done = SilverboxReport(runs=tuple(runs), references=tuple(refs),
                           train=train.samples or (0, train.t.size), hold=hold, figure=figure)
    if verbose:
        print()
        print(done.table())
        if figure is not None:
            print(f"wrote {figure}")
    return done
