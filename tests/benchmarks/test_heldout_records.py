"""bench_heldout.dac_record: the CSTR's logged record (jittered timestamps, missing samples,
a DAC's zero-order-held input), checked against its definition and an independent
integration."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import bench_heldout  # noqa: E402

from thetahat.modelfile import load_model  # noqa: E402
from thetahat.simulation.signals import Multisine  # noqa: E402

CSTR = Path(__file__).resolve().parents[2] / "examples" / "cstr.toml"
#: Noise-free outputs against a per-interval LSODA solution at rtol 1e-11: both solve the same
#: ODE to ~1e-9 relative (the record's rtol), i.e. ~1e-8 on |y| ≤ 20; 1e-6 leaves margin and
#: is still far below the gap to a linearly interpolated input (asserted > 1e-4 below).
HOLD_TOL = 1e-6


def noise_free(spec):
    return dataclasses.replace(spec, scenario=dataclasses.replace(spec.scenario, noise_std=0.0))


@pytest.fixture(scope="module")
def record():
    """2000 samples (the statistics below need them)."""
    return bench_heldout.dac_record(load_model(CSTR), 3, t_end=1999.0)


def test_timestamps_are_jittered_on_the_loggers_grid(record):
    spec, rec = load_model(CSTR), record
    k = np.arange(rec.t.size)
    res = bench_heldout.TIMESTAMP_RESOLUTION
    assert rec.t.size == 2000 and np.all(np.diff(rec.t) > 0)
    assert np.allclose(rec.t / res, np.rint(rec.t / res), atol=1e-6)
    assert np.max(np.abs(rec.t - k)) <= bench_heldout.JITTER_CLIP + res / 2
    # the jitter is there: the sd of the intervals is √2 × JITTER_SD within sampling error
    assert 0.8 < np.std(np.diff(rec.t)) / (np.sqrt(2) * bench_heldout.JITTER_SD) < 1.2
    np.testing.assert_allclose(rec.u, Multisine(spec.scenario.u_amplitudes,
                                                spec.scenario.u_frequencies)(rec.t))


def test_about_one_percent_of_the_outputs_are_missing(record):
    """Binomial(2000, 0.01): mean 20, sd 4.4; [5, 40] is beyond 3 sd either way."""
    rec = record
    lost = np.isnan(rec.y)
    assert np.array_equal(lost[:, 0], lost[:, 1])          # a lost sample loses every output
    assert 5 <= np.count_nonzero(lost[:, 0]) <= 40
    assert not lost[0].any() and not lost[-1].any()
    assert np.all(np.isfinite(rec.y[~lost[:, 0]])) and np.all(np.isfinite(rec.u))


def test_the_plant_saw_the_input_held_between_the_timestamps():
    spec = noise_free(load_model(CSTR))
    s, sc = spec.system, spec.scenario
    rec = bench_heldout.dac_record(spec, 1, t_end=60.0)

    def rhs(t, x, u):
        v = np.concatenate([u, s.C @ x])
        return s.A @ x + s.B @ u + s.E @ np.asarray(s.perturbation.g(v, x, sc.theta))

    def outputs(u_of):
        x, ys = np.asarray(sc.x0, dtype=float), [s.C @ np.asarray(sc.x0, dtype=float)]
        for k in range(rec.t.size - 1):
            sol = solve_ivp(lambda t, z: rhs(t, z, u_of(k, t)), (rec.t[k], rec.t[k + 1]), x,
                            method="LSODA", rtol=1e-11, atol=1e-12)
            x = sol.y[:, -1]
            ys.append(s.C @ x)
        return np.array(ys)

    held = outputs(lambda k, t: rec.u[k])
    ramp = outputs(lambda k, t: rec.u[k] + (rec.u[k + 1] - rec.u[k]) * (t - rec.t[k])
                   / (rec.t[k + 1] - rec.t[k]))
    assert np.nanmax(np.abs(rec.y - held)) < HOLD_TOL
    assert np.nanmax(np.abs(rec.y - ramp)) > 100 * HOLD_TOL
