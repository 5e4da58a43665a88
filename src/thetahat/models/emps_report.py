"""The EMPS benchmark end to end: estimate from the shipped model file, validate, compare.

Used by ``thetahat demo emps``. Reads ``examples/emps.toml`` and the record
``examples/data/emps/DATA_EMPS.mat`` through the normal path (:func:`thetahat.datafile.read_data`
with the file's ``[data]`` table, :func:`thetahat.modelfile.run_estimator`), writes the
estimates, prints the summary, θ̂ beside the published IDIM-LS table, and the benchmark's
closed-loop validation (:func:`thetahat.models.emps.validate`) of θ̂ and of the published θ.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from . import emps

__all__ = ["MODEL_FILE", "EmpsReport", "report"]

#: The shipped model file of the benchmark.
MODEL_FILE = emps.DATA_FILE.parents[2] / "emps.toml"


@dataclass(frozen=True, slots=True, repr=False)
class EmpsReport:
    """What ``thetahat demo emps`` computed.

    Attributes
    ----------
    method : str
    theta_hat : ndarray, shape (4,)
        θ̂ at the end of the record.
    validation : EmpsValidation
        The closed loop simulated with θ̂.
    published : EmpsValidation
        The same with the published IDIM-LS θ.
    estimates : Path
        The CSV written.
    """

    method: str
    theta_hat: NDArray[np.float64]
    validation: emps.EmpsValidation
    published: emps.EmpsValidation
    estimates: Path

    def table(self) -> str:
        """θ̂ beside the published values, then the three eq.-(11) errors of both.

        Returns
        -------
        str
        """
        pub = emps.PUBLISHED
        lines = [f"{'parameter':<10} {self.method + ' θ̂':>14} {'published':>12} {'σ':>8} "
                 f"{'deviation':>10}"]
        for name, est, val, sig in zip(pub.names, self.theta_hat, pub.value, pub.sigma):
            lines.append(f"{name:<10} {est:14.6g} {val:12.6g} {sig:8.4g} "
                         f"{100 * (est - val) / abs(val):9.2f} %")
        lines.append("")
        lines.append(f"{'relative error (eq. 11)':<25} {self.method + ' θ̂':>12} "
                     f"{'published θ':>12} {'published':>10}")
        lines.append(f"{'':<25} {'':>12} {'(ours)':>12} {'(Simulink)':>10}")
        for key in ("position", "velocity", "force"):
            lines.append(f"{key:<25} {getattr(self.validation, key):10.4g} % "
                         f"{getattr(self.published, key):10.4g} % "
                         f"{emps.PUBLISHED_VALIDATION[key]:8.4g} %")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"EmpsReport(method={self.method!r}, theta_hat={self.theta_hat.tolist()}, "
                f"validation={self.validation!r})")


def report(*, out: Path | str = "out", method: str = "paper", verbose: bool = True
           ) -> EmpsReport:
    """Estimate θ on DATA_EMPS with the shipped model file and validate it (eq. 11).

    Parameters
    ----------
    out : path
        Output folder (created); the estimates go to ``out/emps_<method>.csv``.
    method : {"paper", "guarded", "mle"}
        The estimator.
    verbose : bool
        Print the summary and the tables.

    Returns
    -------
    EmpsReport

    Raises
    ------
    ModelFileError
        The model file or the record is missing (an installed package without the
        repository's ``examples/``).
    """
    from ..datafile import read_data, write_estimates
    from ..modelfile import load_model, run_estimator
    from ..studies.metrics import estimate_summary

    spec = load_model(MODEL_FILE)
    data = read_data(emps.DATA_FILE, spec)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_estimator(spec, data.t, data.u, data.y, method=method)
    path = Path(out) / f"emps_{method}.csv"
    write_estimates(path, result, spec)
    theta_hat = np.array(result.theta_hat[-1], dtype=np.float64)
    record = emps.load()
    done = EmpsReport(method=method, theta_hat=theta_hat,
                      validation=emps.validate(theta_hat, record),
                      published=emps.validate(emps.PUBLISHED.value, record), estimates=path)
    if verbose:
        notes = [f"{w.category.__name__}: {w.message}" for w in caught]
        print(f"EMPS (Janot, Gautier & Brunot 2019): {data.t.size} samples, "
              f"{MODEL_FILE.name}, method {method}; wrote {path}")
        print(estimate_summary(result, spec.parameter_names, warnings=notes))
        print(done.table())
    return done
