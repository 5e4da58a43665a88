"""The Silverbox benchmark: a measured electronic Duffing oscillator, its splits and the literature.

The Silverbox (Wigren & Schoukens 2013) is an electronic circuit built to behave as a forced
Duffing oscillator, m ÿ + d ẏ + k₁ y + k₃ y³ = u: V1 is the input, V2 the output, sampled at
fs = 10⁷/2¹⁴ ≈ 610.35 Hz, 131 072 samples. The record shipped in
``examples/data/silverbox/`` (see its README for the source, licence and citation) holds an
"arrow head" (Gaussian noise of linearly rising amplitude, samples 0 – 40 600) and ten
realisations of an odd random-phase multisine. ``examples/silverbox.toml`` is the estimation
model: its ``[data]`` table maps V1 → u and V2 → y (less the output's offset), gives the time
base and names the benchmark's standard splits (:data:`TEST_SPLITS` and ``train``), and its
``samples = "train"`` makes every estimator read the training split only.

This module holds what belongs to the benchmark, not to an estimator: :func:`load` (the whole
record, through the model file's mapping), :data:`INIT_WINDOW` and :data:`TEST_SPLITS` (the
benchmark's validation protocol), :func:`validate` (θ's free-run simulation of the test
splits, :func:`thetahat.studies.validation.validate_free_run`), and :data:`LITERATURE`, the
published test errors we could trace to a table.

References
----------
T. Wigren and J. Schoukens, "Three free data sets for development and benchmarking in
nonlinear system identification", European Control Conference, Zürich, 2013, pp. 2933–2938.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ModelFileError
from ..io.record import DataRecord
from ..studies.validation import FreeRunValidation

__all__ = ["DATA_FILE", "FS", "INIT_WINDOW", "LITERATURE", "MODEL_FILE", "PublishedResult",
           "TEST_SPLITS", "TRAIN_SPLIT", "load", "splits", "validate"]

#: The record shipped with the repository.
DATA_FILE = (Path(__file__).resolve().parents[3] / "examples" / "data" / "silverbox"
             / "SNLS80mV.mat")
#: The estimation model (its [data] table maps the record and names the splits).
MODEL_FILE = DATA_FILE.parents[2] / "silverbox.toml"
#: The sampling frequency (Hz): 10⁷ / 2¹⁴.
FS = 1e7 / 2 ** 14
#: Samples at the start of each test split from which a model may fit its initial state, not
#: scored (the benchmark's loader of nonlinearbenchmark.org, ``nonlinear_benchmarks``).
INIT_WINDOW = 50
#: The training split's name in the model file's [data.segments].
TRAIN_SPLIT = "train"
#: The test splits' names in the model file's [data.segments], in the literature's order: the
#: multisine held back, the full arrow head (whose amplitude exceeds the training data's) and
#: its part without extrapolation.
TEST_SPLITS = ("test_multisine", "test_arrow_full", "test_arrow_no_extrapolation")


@dataclass(frozen=True, slots=True)
class PublishedResult:
    """A published free-run RMS error on a Silverbox test split.

    Attributes
    ----------
    model : str
        What was identified.
    kind : str
        "linear", "black box", "grey box" or "physical".
    split : str
        The test split (a name of :data:`TEST_SPLITS`).
    rms_mV : float
        RMS of the simulation error (mV).
    source : str
        Where the figure is printed (paper, table).
    """

    model: str
    kind: str
    split: str
    rms_mV: float
    source: str


_CRUZ = ("Cruz, Renczes, Runacres & Decuyper, \"State-space Kolmogorov-Arnold networks for "
         "interpretable nonlinear system identification\", IEEE Control Systems Letters 2025 "
         "(arXiv:2506.16392), Table I")
#: Published test errors on the full arrow head (40 000 samples, with extrapolation), as
#: collected in one table: the best linear approximation (Wigren & Schoukens 2013), the
#: polynomial nonlinear state-space model (Paduart et al., Automatica 2010), the deep
#: subspace-encoder network (Beintema, Tóth & Schoukens, L4DC 2021) and the state-space
#: Kolmogorov–Arnold network (Cruz et al. 2025), in the units of the source (V, here mV).
LITERATURE: tuple[PublishedResult, ...] = (
    PublishedResult("best linear approximation", "linear", "test_arrow_full", 13.5, _CRUZ),
    PublishedResult("PNLSS (Paduart et al. 2010)", "black box", "test_arrow_full", 0.3, _CRUZ),
    PublishedResult("deep subspace encoder (Beintema et al. 2021)", "black box",
                    "test_arrow_full", 1.4, _CRUZ),
    PublishedResult("SS-KAN (Cruz et al. 2025)", "grey box", "test_arrow_full", 3.9, _CRUZ),
)


def _spec():
    from ..modelfile import load_model
    if not MODEL_FILE.is_file():
        raise ModelFileError(f"Silverbox model file {MODEL_FILE} not found (an installed "
                             f"package without the repository's examples/?).")
    return load_model(MODEL_FILE)


def splits() -> dict[str, tuple[int, int]]:
    """The benchmark's splits, as the model file's ``[data.segments]`` names them.

    Returns
    -------
    dict of str to (int, int)
        Name → (start, stop), 0-based, half-open.

    Examples
    --------
    >>> from thetahat.models import silverbox
    >>> silverbox.splits()["test_multisine"]
    (105712, 127400)
    """
    data = _spec().data
    if data is None:
        raise ModelFileError(f"{MODEL_FILE} has no [data] table.")
    return {name: (start, stop) for name, start, stop in data.segments}


def load(path: str | Path | None = None) -> DataRecord:
    """The whole Silverbox record in the model's signals (u = V1, y = V2 − y₀, t from fs).

    Parameters
    ----------
    path : str or Path, optional
        A MAT file with V1 and V2 (default: :data:`DATA_FILE`).

    Returns
    -------
    DataRecord
        Every sample (the file's ``samples = "train"`` is the estimators' choice, not the
        record's).

    Raises
    ------
    ModelFileError
        The file or the model file is missing or unreadable.

    Examples
    --------
    >>> from thetahat.models import silverbox
    >>> record = silverbox.load()
    >>> record.t.size, round(float(1.0 / (record.t[1] - record.t[0])), 4)
    (131072, 610.3516)
    """
    from ..io.datafile import read_data
    path = DATA_FILE if path is None else Path(path)
    if not path.is_file():
        raise ModelFileError(f"Silverbox data file {path} not found; pass the path of "
                             f"SNLS80mV.mat (in the repository: examples/data/silverbox/).")
    return read_data(path, _spec().layout, samples="all")


def validate(theta: ArrayLike, record: DataRecord | None = None, *, hold: str = "foh",
             names: tuple[str, ...] = TEST_SPLITS,
             substeps: int | None = None) -> FreeRunValidation:
    """The benchmark's validation of θ: free-run simulations of the test splits.

    On each split, x(0) is fitted to its first :data:`INIT_WINDOW` samples, the split is
    simulated from it with its inputs and the error is taken over the rest
    (:func:`thetahat.studies.validation.validate_free_run`): RMS in volts (× 1e3 for mV) and
    the fit in %.

    Parameters
    ----------
    theta : array_like, shape (5,)
        (m, d, k1, k3, u0).
    record : DataRecord, optional
        Default: :func:`load`.
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        The input between samples, as the estimate assumed.
    names : tuple of str
        The splits (default :data:`TEST_SPLITS`).
    substeps : int, optional
        RK4 steps per sample (default: converged).

    Returns
    -------
    FreeRunValidation

    Examples
    --------
    >>> from thetahat.models import silverbox
    >>> check = silverbox.validate([5.167e-6, 2.157e-4, 0.9523, 3.789, 6.22e-3],
    ...                            names=("test_multisine",))
    >>> bool(1e3 * check["test_multisine"].rms[0] < 1.0)      # mV, the linear hold
    True
    """
    from ..studies.validation import validate_free_run
    spec = _spec()
    record = load() if record is None else record
    every = splits()
    chosen = {}
    for name in names:
        if name not in every:
            raise ModelFileError(f"no split {name!r} in {MODEL_FILE}; it names {list(every)}.")
        chosen[name] = every[name]
    return validate_free_run(spec.system, np.asarray(theta, dtype=np.float64), record.t,
                             record.u, record.y, chosen, hold=hold, init_window=INIT_WINDOW,
                             substeps=substeps)
