"""Stage 2's input samples ũ (estimation.statistical.input_hold): the linear hold of ũ carries
a smooth input's mean over each interval to fourth order; inputs the sampling does not resolve
(steps, a PRBS, white noise, a zero-order-hold staircase) are kept as sampled; a stream cut into
blocks gets the samples of one call (so ``step`` and ``run`` agree).
"""

from __future__ import annotations

import numpy as np
import pytest

from thetahat.estimation.statistical.input_hold import smooth_input


def _interval_mean_errors(wh: float) -> tuple[float, float]:
    """Max error of the interval mean of sin under the linear hold of u and of ũ (after the
    first samples), for ω h = wh, in units of the amplitude."""
    h = 1.0
    w = wh / h
    t = np.arange(400) * h
    u = np.sin(w * t + 0.3)
    exact = (np.cos(w * t[:-1] + 0.3) - np.cos(w * t[1:] + 0.3)) / (w * h)
    ut = smooth_input(u[:, None])[0][:, 0]
    lin = np.abs((u[:-1] + u[1:]) / 2 - exact)[10:].max()
    new = np.abs((ut[:-1] + ut[1:]) / 2 - exact)[10:].max()
    return float(lin), float(new)


@pytest.mark.parametrize("wh", [0.05, 0.1, 0.2, 0.4])
def test_the_linear_hold_of_u_tilde_is_fourth_order(wh):
    """The linear hold's error is (ωh)²/12 (the trapezoid rule's h²ü/12) (to 5 % here); ũ's is below (ωh)⁴/8 — at least
    ωh/3 times smaller — and falls ≥ 12× when h halves (16× for a fourth-order error)."""
    lin, new = _interval_mean_errors(wh)
    assert abs(lin / (wh ** 2 / 12) - 1.0) < 0.05
    assert new <= wh ** 4 / 8
    _, new_half = _interval_mean_errors(wh / 2)
    assert new / new_half >= 12.0


@pytest.mark.parametrize("kind", ["step", "prbs", "white", "staircase"])
def test_inputs_the_sampling_does_not_resolve_are_kept(kind):
    """ρ = |Δ²u| / |Δu| ≥ 1 for these (a step √2, a PRBS or white noise ≈ √3, a staircase
    held 5 samples ≈ √2): ũ = u exactly."""
    rng = np.random.default_rng(0)
    n = 500
    u = {"step": np.repeat([0.0, 1.0], n // 2),
         "prbs": rng.choice([-1.0, 1.0], size=n),
         "white": rng.standard_normal(n),
         "staircase": np.repeat(rng.standard_normal(n // 5), 5)}[kind]
    assert np.array_equal(smooth_input(u[:, None])[0][:, 0], u)


def test_blocks_give_the_samples_of_one_call():
    """Two channels (one smooth, one a PRBS) cut into blocks of 1–37 samples: the same ũ as
    one call, to the last bit (the running sums add the same terms in the same order)."""
    rng = np.random.default_rng(1)
    N = 600
    t = np.arange(N) * 1e-3
    U = np.column_stack([np.sin(2 * np.pi * 7.0 * t) + 0.3 * np.sin(2 * np.pi * 31.0 * t),
                         rng.choice([-1.0, 1.0], size=N)])
    whole, _ = smooth_input(U)
    parts, hist, k = [], None, 0
    while k < N:
        b = int(rng.integers(1, 38))
        Ut, hist = smooth_input(U[k:k + b], hist)
        parts.append(Ut)
        k += b
    assert np.array_equal(np.vstack(parts), whole)
    assert not np.array_equal(whole[:, 0], U[:, 0])      # the smooth channel was corrected
    assert np.array_equal(whole[:, 1], U[:, 1])          # the PRBS was not


@pytest.mark.parametrize("m", [1, 3])
def test_a_stream_of_single_samples_gives_the_samples_of_one_call(m):
    """One sample at a time (a stream's step, which takes the scalar path after three
    samples): the same ũ and the same history as one call on the record, to the last bit, on
    a smooth channel, a PRBS, a staircase (a DAC's zero-order hold) and a channel that turns
    from smooth to noisy half-way (ρ crosses 1, so correction stops)."""
    rng = np.random.default_rng(4)
    N = 400
    t = np.arange(N) * 1e-3
    kinds = [np.sin(2 * np.pi * 9.0 * t),
             rng.choice([-1.0, 1.0], size=N),
             np.repeat(rng.normal(size=N // 8), 8),
             np.where(t < 0.2, np.sin(2 * np.pi * 3.0 * t), rng.normal(size=N))]
    for first in range(len(kinds) - m + 1):
        U = np.column_stack(kinds[first:first + m])
        whole, end = smooth_input(U)
        hist, rows = None, []
        for k in range(N):
            Ut, hist = smooth_input(U[k:k + 1], hist)
            rows.append(Ut)
        assert np.array_equal(np.vstack(rows), whole)
        assert np.array_equal(hist.u_last, end.u_last)
        assert np.array_equal(hist.d1, end.d1) and np.array_equal(hist.d2, end.d2)
    switched = smooth_input(kinds[3][:, None])[0][:, 0] != kinds[3]
    assert switched[3:N // 2].all() and switched[N // 2 + 2:].sum() == 0


def test_stage2_samples_of_a_long_record_come_in_blocks_with_the_same_numbers(monkeypatch):
    """``stage2_samples`` under "smooth" takes a record longer than EVAL_BLOCK a block at a
    time (its differences and sums a block long), each block carrying the history: the ũ and
    the history of one call, to the bit — with the default block on 2¹⁷ + 1 samples (the last
    block one sample, the stream's scalar path) and with blocks of 50."""
    import thetahat.estimation.statistical.input_hold as input_hold
    rng = np.random.default_rng(2)
    for N, block in ((2 ** 17 + 1, input_hold.EVAL_BLOCK), (1_001, 50)):
        monkeypatch.setattr(input_hold, "EVAL_BLOCK", block)
        t = np.arange(N) * 1e-3
        U = np.column_stack([np.sin(2 * np.pi * 7.0 * t), rng.choice([-1.0, 1.0], size=N)])
        want, hist = smooth_input(U)
        got, ghist = input_hold.stage2_samples(U, "smooth")
        assert np.array_equal(got, want) and got.flags.c_contiguous
        for name in ("u_last", "d1", "d2"):
            assert np.array_equal(getattr(ghist, name), getattr(hist, name)), name
        assert not np.array_equal(want[:, 0], U[:, 0])
