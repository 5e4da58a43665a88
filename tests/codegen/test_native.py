"""The observer on the C printed from its formulas (thetahat.codegen.native), as runner's choice.

Agreement is against the Python observer's own run, the conformance matrix's reference, to
its tolerance AGREE_RTOL = 1e-9: the C sums in another order and takes the record's mean step
(the steps of np.arange differ from it by rounding, ~1e-13 relative), rounding only (measured
≤ 3e-13 on these records), a margin above 1000×.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat.codegen.loader import find_compiler

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler (cc or $CC)")

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
MODEL_FILES = ("lugre", "prop1", "prop2", "two_inertia")
AGREE_RTOL = 1e-9


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    scale = np.maximum(np.max(np.abs(b), axis=0), np.finfo(float).tiny)
    return float(np.max(np.abs(a - b) / scale))


def case(name: str):
    """(spec, observer with nan_policy="skip", t, u, y, state0): the file's scenario for 2 s
    (lugre: 0.4 s at its 1 kHz), uniform, with a gap of missing samples."""
    from thetahat.modelfile import build_observer, load_model
    from thetahat.modelfile.study import simulate_model
    spec = load_model(EXAMPLES / f"{name}.toml")
    run = simulate_model(spec, 3, t_end=0.4 if name == "lugre" else 2.0)
    N = run.t.size
    u, y = run.u.reshape(N, -1), run.y.reshape(N, -1).copy()
    y[N // 2:N // 2 + 10] = np.nan
    obs = build_observer(spec, nan_policy="skip")
    s0 = obs.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    return spec, obs, run.t, u, y, s0


def never() -> None:
    raise AssertionError("the fallback ran: the record should have run in C")


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("THETAHAT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("THETAHAT_C", raising=False)


@pytest.mark.parametrize("hold", ("zoh", "foh"))
@pytest.mark.parametrize("name", MODEL_FILES)
def test_c_run_equals_the_python_run(name, hold):
    from thetahat.codegen.native import NativeObserver
    spec, obs, t, u, y, s0 = case(name)
    obs = obs.with_run_options(hold=hold)
    ref = obs.run(t, u, y, state0=s0)
    calls = []
    reporting = obs.with_run_options(progress=lambda a, b: calls.append((a, b)))
    res = NativeObserver(reporting, never).run(t, u, y, state0=s0)
    for field in ("x_hat", "phi_hat", "theta_hat"):
        assert rel_err(getattr(res, field), getattr(ref, field)) <= AGREE_RTOL, field
    assert (res.x_hat_refined is None) == (ref.x_hat_refined is None)
    if ref.x_hat_refined is not None:
        assert rel_err(res.x_hat_refined, ref.x_hat_refined) <= AGREE_RTOL
    assert np.array_equal(res.skipped, ref.skipped) and res.skipped.any()
    assert spec.system.parameter_set.contains(res.theta_hat, tol=1e-12).all()
    assert np.ptp(ref.theta_hat, axis=0).max() > 1e-3      # the law moved θ̂: the case tests it
    assert calls[-1] == (t.size - 1, t.size - 1)


@pytest.mark.parametrize("name", MODEL_FILES)
def test_a_stream_steps_in_c_as_the_observer_steps(name):
    """NativeObserver.step (a stream, zero-order hold) runs the C of the stream's step length
    and agrees with the observer's own steps, NaN gap included, to the run's tolerance."""
    from thetahat.codegen.native import NativeObserver
    spec, obs, t, u, y, s0 = case(name)
    fast = NativeObserver(obs, never)
    h = float(t[1] - t[0])
    assert fast.steps_in_c(h)
    a, b, A, B = s0.copy(), s0.copy(), [], []
    for k in range(t.size):
        a, b = fast.step(a, u[k], y[k], h), obs.step(b, u[k], y[k], h)
        A.append(a)
        B.append(b)
    assert rel_err(np.array(A), np.array(B)) <= AGREE_RTOL


@pytest.mark.parametrize("name", MODEL_FILES)
def test_read_and_step_in_c_is_read_estimates_then_step(name):
    """NativeObserver.read_and_step (the guarded stream's stage 1): the estimates of the state
    it is given, bit for bit ``read_estimates``', and the state ``step`` returns, bit for bit
    (the same C step), the given state untouched, NaN gap included."""
    from thetahat.codegen.native import NativeObserver
    spec, obs, t, u, y, s0 = case(name)
    fast = NativeObserver(obs, never)
    h = float(t[1] - t[0])
    s = s0.copy()
    for k in range(t.size):
        kept = s.copy()
        x, th, x2, nxt = fast.read_and_step(s, u[k], y[k], h)
        rx, rth, rx2 = fast.read_estimates(s, u[k], y[k])
        np.testing.assert_array_equal(x, rx)
        np.testing.assert_array_equal(th, rth)
        assert (x2 is None) == (rx2 is None) and (x2 is None or np.array_equal(x2, rx2))
        np.testing.assert_array_equal(nxt, fast.step(s, u[k], y[k], h))
        np.testing.assert_array_equal(s, kept)
        s = nxt


@pytest.mark.parametrize("name", MODEL_FILES)
def test_stepped_is_step_on_a_copy(name):
    """CObserver.stepped (the stream's C call through buffers allocated once): the status and
    state of ``step`` on a copy, bit for bit, the state passed in untouched; other shapes are
    a DimensionError that says what the step takes."""
    from thetahat.codegen.generate import generate_c
    from thetahat.codegen.native import load_cached
    from thetahat.errors import DimensionError
    spec, obs, t, u, y, s0 = case(name)
    h = float(t[1] - t[0])
    c = load_cached(generate_c(obs, dt=h, name="thetahat_observer"))
    s = s0.copy()
    for k in range(t.size):
        kept, ref = s.copy(), s.copy()
        status, nxt = c.stepped(s, u[k], y[k])
        assert status == c.step(ref, u[k], y[k]) == 0
        np.testing.assert_array_equal(nxt, ref)
        np.testing.assert_array_equal(s, kept)
        s = nxt
    for bad in ((s[:-1], u[0], y[0]), (s, u[0], np.append(y[0], 0.0)),
                (s, np.append(u[0], 0.0), y[0])):
        with pytest.raises(DimensionError, match="takes a state of"):
            c.stepped(*bad)


@pytest.mark.parametrize("name", MODEL_FILES)
def test_run_rows_writes_into_the_rows_it_is_given(name):
    """CObserver.run_rows(out=…) (the record run's row blocks: no second copy of the record)
    writes the same rows as into arrays of its own, bit for bit, into the arrays given; arrays
    of another precision or layout are not written (new ones are returned)."""
    from thetahat.codegen.generate import generate_c
    from thetahat.codegen.native import load_cached
    spec, obs, t, u, y, s0 = case(name)
    c = load_cached(generate_c(obs, dt=float(t[1] - t[0]), name="thetahat_observer"))
    N = t.size
    U = np.ascontiguousarray(u if u.shape[1] else np.zeros((N, 1)), dtype=np.float64)
    Y = np.ascontiguousarray(np.nan_to_num(y), dtype=np.float64)
    S_ref, PHI_ref, status, _ = c.run_rows(s0.copy(), U, Y)
    assert status == 0
    S, PHI = np.full((N + 3, S_ref.shape[1]), -1.0), np.full((N + 3, PHI_ref.shape[1]), -1.0)
    rows, phi, status, _ = c.run_rows(s0.copy(), U, Y, out=(S[2:N + 2], PHI[2:N + 2]))
    assert status == 0 and np.shares_memory(rows, S) and np.shares_memory(phi, PHI)
    np.testing.assert_array_equal(S[2:N + 2], S_ref)
    np.testing.assert_array_equal(PHI[2:N + 2], PHI_ref)
    assert np.all(S[:2] == -1.0) and np.all(S[N + 2:] == -1.0)     # nothing outside the rows
    strided = np.full((N, 2 * S_ref.shape[1]), -1.0)[:, ::2]       # not C-contiguous
    rows, _, _, _ = c.run_rows(s0.copy(), U, Y, out=(strided, PHI[2:N + 2]))
    assert not np.shares_memory(rows, strided) and np.all(strided == -1.0)
    np.testing.assert_array_equal(rows, S_ref)


def test_a_stream_step_the_c_cannot_take_is_the_observers():
    """Another step length than the stream's first runs the observer's step (bit for bit), and
    a NaN under nan_policy="raise" raises the observer's error."""
    from thetahat.codegen.native import NativeObserver
    from thetahat.errors import NonFiniteError
    spec, obs, t, u, y, s0 = case("prop1")
    fast = NativeObserver(obs, never)
    h = float(t[1] - t[0])
    s1 = fast.step(s0, u[0], y[0], h)
    assert fast.steps_in_c(h) and not fast.steps_in_c(1.5 * h)
    assert np.array_equal(fast.step(s1, u[1], y[1], 1.5 * h), obs.step(s1, u[1], y[1], 1.5 * h))
    from thetahat.modelfile import build_observer
    strict = NativeObserver(build_observer(spec, nan_policy="raise"), never)
    with pytest.raises(NonFiniteError, match="nan_policy"):
        strict.step(s0, u[0], np.full_like(y[0], np.nan), h)


def test_progress_chunks_carry_the_state(monkeypatch):
    """Runs cut into pieces for progress reports continue each from the last row: the same
    numbers as one piece, bit for bit."""
    import thetahat.codegen.native as native
    _, obs, t, u, y, s0 = case("lugre")
    whole = native.NativeObserver(obs, never).run(t, u, y, state0=s0)
    monkeypatch.setattr(native, "PROGRESS_EVERY", 37)
    calls = []
    reporting = obs.with_run_options(progress=lambda a, b: calls.append(a))
    cut = native.NativeObserver(reporting, never).run(t, u, y, state0=s0)
    assert len(calls) > 10
    assert np.array_equal(cut.x_hat, whole.x_hat) and np.array_equal(cut.theta_hat,
                                                                     whole.theta_hat)


def test_irregular_record_runs_in_the_fallback():
    from thetahat.codegen.native import NativeObserver
    _, obs, t, u, y, s0 = case("prop1")
    keep = np.ones(t.size, dtype=bool)
    keep[5::7] = False                                   # steps of 1 and 2 samples
    used = []

    def fallback():
        used.append(True)
        return obs
    res = NativeObserver(obs, fallback).run(t[keep], u[keep], y[keep], state0=s0)
    ref = obs.run(t[keep], u[keep], y[keep], state0=s0)
    assert used == [True]
    assert np.array_equal(res.theta_hat, ref.theta_hat)


def test_a_failing_c_run_reports_the_observers_status():
    """A nonzero C status is the Status of its code, reported as the observer reports it: the
    same error (``throw=True``), or the same status, message and ``failed_at`` with the rows
    from there NaN (``throw=False``); the fallback is not asked."""
    from thetahat.codegen.native import NativeObserver
    from thetahat.errors import NonFiniteError
    from thetahat.estimation.status import Status
    _, obs, t, u, y, s0 = case("prop1")
    y = y * 1e100           # the state leaves the bound (1e200 is refused: limits)
    with pytest.raises(NonFiniteError) as ref:
        obs.run(t, u, y, state0=s0)
    with pytest.raises(NonFiniteError) as got:
        NativeObserver(obs, never).run(t, u, y, state0=s0)
    assert str(got.value) == str(ref.value)
    want = obs.run(t, u, y, state0=s0, throw=False)
    res = NativeObserver(obs, never).run(t, u, y, state0=s0, throw=False)
    assert want.status == res.status == Status.DIVERGED and res.message == want.message
    assert res.failed_at == want.failed_at and 0 < res.failed_at < t.size
    assert np.isnan(res.theta_hat[res.failed_at:]).all()
    assert np.isfinite(res.theta_hat[:res.failed_at]).all()
    assert res.message == str(ref.value)
    with pytest.raises(NonFiniteError) as again:
        res.raise_for_status()
    assert str(again.value) == str(ref.value)


def test_library_is_built_once_per_cache(monkeypatch, tmp_path):
    """A second observer of the same model loads the cached library: the compiler is not run
    (the process's own table of loaded libraries emptied: what a new process finds)."""
    import thetahat.codegen.native as native
    import thetahat.codegen.native_cache as native_cache
    _, obs, t, u, y, s0 = case("prop2")
    monkeypatch.setattr(native_cache, "_loaded", {})       # loaded by an earlier test
    first = native.NativeObserver(obs, never).run(t, u, y, state0=s0)
    libs = list((tmp_path / "cache").glob("thetahat_c_*.so"))
    assert len(libs) == 1 and len(list((tmp_path / "cache").glob("thetahat_c_*.json"))) == 1

    def no_build(*args, **kwargs):
        raise AssertionError("compiled again")
    monkeypatch.setattr(native_cache, "build", no_build)
    monkeypatch.setattr(native_cache, "_loaded", {})
    again = native.NativeObserver(obs, never).run(t, u, y, state0=s0)
    assert np.array_equal(first.theta_hat, again.theta_hat)


def test_runner_chooses_c_and_thetahat_c_0_turns_it_off(monkeypatch):
    from thetahat.codegen.native import NativeObserver
    from thetahat.estimation.drive import runner
    _, obs, t, *_ = case("prop1")
    assert isinstance(runner(obs, t, compiled=True), NativeObserver)
    monkeypatch.setenv("THETAHAT_C", "0")
    assert not isinstance(runner(obs, t, compiled=True), NativeObserver)


def test_without_numba_the_c_runs_and_nothing_is_noted(monkeypatch):
    """numba missing changes nothing for a uniform record the C takes: no fallback, no note."""
    import sys
    import warnings

    from thetahat.codegen.native import NativeObserver
    from thetahat.estimation.drive import runner
    spec, obs, t, u, y, s0 = case("prop1")
    monkeypatch.setitem(sys.modules, "numba", None)       # `import numba` now fails
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast = runner(obs, t, compiled=True)
        assert isinstance(fast, NativeObserver)
        res = fast.run(t, u, y, state0=s0)
    assert rel_err(res.theta_hat, obs.run(t, u, y, state0=s0).theta_hat) <= AGREE_RTOL


def test_row_blocks_give_the_whole_runs_numbers_and_bound_its_memory(monkeypatch):
    """A record longer than ROW_BLOCK runs a block of state rows at a time, their columns
    copied out (RecordRows): bit for bit the numbers of one block, and the run holds its
    outputs plus about its inputs' copies — not the record's state rows besides.

    Memory is numpy's, traced: beyond the result's arrays the run measured 0.49× the input
    arrays' bytes (its C-contiguous copies of u and y, the present mask, one block of rows)
    with 1,000-row blocks, and 2.75× with the record as one block (the state rows and φ̂ held
    whole until copied); the bound 1× has a 2× margin over the first and fails the second.
    """
    import tracemalloc

    import thetahat.codegen.native as native
    _, obs, t, u, y, s0 = case("lugre")
    reps = 125                                       # 50,125 samples: 50 blocks of 1,000
    T = np.arange(t.size * reps) * (t[1] - t[0])
    U, Y = np.tile(u, (reps, 1)), np.tile(y, (reps, 1))
    monkeypatch.setattr(native, "ROW_BLOCK", T.size)
    whole = native.NativeObserver(obs, never).run(T, U, Y, state0=s0)
    monkeypatch.setattr(native, "ROW_BLOCK", 1_000)
    runner = native.NativeObserver(obs, never)
    runner.run(T[:500], U[:500], Y[:500], state0=s0)             # builds and loads the C
    tracemalloc.start()
    try:
        cut = runner.run(T, U, Y, state0=s0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    for name in ("x_hat", "theta_hat", "phi_hat"):
        assert np.array_equal(getattr(cut, name), getattr(whole, name)), name
    assert np.array_equal(cut.diagnostics.x_hat_refined, whole.diagnostics.x_hat_refined)
    outputs = sum(a.nbytes for a in (cut.t, cut.x_hat, cut.theta_hat, cut.phi_hat,
                                     cut.skipped, cut.diagnostics.x_hat_refined))
    assert peak - outputs <= 1.0 * (T.nbytes + U.nbytes + Y.nbytes)


def test_a_failure_in_a_later_block_stops_where_one_block_stops(monkeypatch):
    """The failed step's sample, status and message do not depend on the blocks."""
    import thetahat.codegen.native as native
    _, obs, t, u, y, s0 = case("prop1")
    y = y * 1e100
    whole = native.NativeObserver(obs, never).run(t, u, y, state0=s0, throw=False)
    monkeypatch.setattr(native, "ROW_BLOCK", max(whole.failed_at // 3, 1))
    cut = native.NativeObserver(obs, never).run(t, u, y, state0=s0, throw=False)
    assert whole.failed_at > 3 and (cut.failed_at, cut.status, cut.message) == (
        whole.failed_at, whole.status, whole.message)
    assert np.array_equal(cut.theta_hat, whole.theta_hat, equal_nan=True)
