"""Records for the tests: a shipped model's scenario, or the head of a measured record."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from thetahat.modelfile import load_model, simulate_model

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def shipped_record(name: str, samples: int = 12_000):
    """(spec, t, U, Y, θ or None): ``samples`` samples of a shipped model's scenario (seed 1)
    or of a measured record (EMPS's; Silverbox's training split)."""
    if name == "emps":
        from thetahat.models import emps
        rec = emps.load()
        spec, t, u, y, theta = load_model(EXAMPLES / "emps.toml"), rec.t, rec.u, rec.y, None
    elif name == "silverbox":
        from thetahat.io.datafile import read_data
        from thetahat.models import silverbox
        spec = load_model(silverbox.MODEL_FILE)
        rec = read_data(silverbox.DATA_FILE, spec.layout)
        t, u, y, theta = rec.t - rec.t[0], rec.u, rec.y, None
    else:
        spec = load_model(EXAMPLES / f"{name}.toml")
        d = simulate_model(spec, 1, t_end=samples / spec.scenario.fs)
        t, u, y, theta = d.t, d.u, d.y, spec.scenario.theta
    N = min(t.size, samples)
    U, Y = np.asarray(u)[:N].reshape(N, -1), np.asarray(y)[:N].reshape(N, -1)
    return spec, t[:N], U, Y, theta
