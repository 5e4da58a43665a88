"""The tutorial's path on a newcomer's model: a wrong θ̂ never goes without a warning.

The issue "Honest on a user's own model": a newcomer follows docs/tutorial.md — the file's
defaults first (``run_estimator`` with no method: the guarded estimator), then the paper's
observer (``method="paper"``) — on a model the library was not tuned for. Whatever the method,
its final θ̂ is either within PAPER_SDS of its own reported Cramér–Rao sd of the truth, or
the run carries a warning that says why not (a trust-report finding or a ConvergenceWarning).
Run on the newcomer's Stribeck model (examples/stribeck.toml) and three more (the wheel, the
spring with friction, the two-inertia drive), on a part of each scenario to keep the file
within minutes (marked slow)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import ConvergenceWarning, ThetahatWarning
from thetahat.modelfile import load_model, run_estimator, simulate_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: The issue's target: θ̂ within 3 × its own reported sd of the truth, or a warning.
PAPER_SDS = 3.0
#: The part of each scenario simulated (s): several periods of its input, and enough samples
#: for the statistical checks.
T_END = {"stribeck": 10.0, "wheel": 5.0, "spring_friction": 10.0, "two_inertia": None}


def _run(spec, d, method):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_estimator(spec, d.t, d.u, d.y, method=method)
    return res, caught


@pytest.mark.slow
@pytest.mark.parametrize("method", [None, "paper"])
@pytest.mark.parametrize("name", sorted(T_END))
def test_a_wrong_theta_hat_carries_a_warning_that_says_why(name, method):
    spec = load_model(EXAMPLES / f"{name}.toml")
    d = simulate_model(spec, 0, t_end=T_END[name])
    res, caught = _run(spec, d, method)
    theta = np.asarray(spec.scenario.theta)
    sd = res.trust.crlb_sd
    off = np.abs(res.theta_hat[-1] - theta) / sd
    warned = [str(w.message) for w in caught
              if issubclass(w.category, (ThetahatWarning, ConvergenceWarning))]
    if not np.all(off <= PAPER_SDS):
        assert warned, (f"{name} ({method or 'default'}): θ̂ {np.round(off, 1)} sd from θ "
                        "without a warning")
        # the warning is the report's and is in the summary as well
        from thetahat.studies.metrics import estimate_summary
        assert "warnings: none" not in estimate_summary(res, warnings=caught)
