"""Every shipped model file's [scenario] (or the default one) simulates: thetahat sweep and tune
start from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat.modelfile import load_model, simulate_model

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.toml"))


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_scenario_simulates(path):
    spec = load_model(path)
    d = simulate_model(spec, 0, t_end=min(spec.scenario.t_end, 5.0))
    assert np.all(np.isfinite(np.asarray(d.y))) and d.t.size >= 2
