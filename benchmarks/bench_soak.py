"""Soak: a 10⁷-sample stream through the compiled observer, memory flat and θ̂ still right.

Run:  .venv/bin/python benchmarks/bench_soak.py [--samples 10000000] [--chunk 100000] [--json out/bench_soak.json]

The model is the package's example (``thetahat.modelfile.EXAMPLE_MODEL``: an oscillator with
the monotone perturbation g = (2 + sin y)(θ + θ³/3) of Proposition 3, θ = 1 here). Its record is
periodic: the plant is driven by u = sin(2πt/P) + 0.5 sin(6πt/P), P = 2 s, integrated by
``solve_ivp`` (rtol 1e-10) until the periodic steady state, and one period, sampled at
dt = 1 ms, is repeated for as long as the stream lasts (no 10⁷-row array is ever built: the
soak measures the estimator, not the data).

Two ways of streaming the same samples, each from θ̂(0) = 0:

* ``step``: :meth:`CompiledObserver.step` once per sample, as a sensor loop would;
* ``run_chunks``: :meth:`CompiledObserver.run` on chunks of ``--chunk`` samples, each starting
  from the last state of the one before.

Memory is the process's resident set (Linux ``/proc/self/statm``), read at every tenth of the
stream; the figure of merit is the growth above the resident set just before the stream (the
interpreter, NumPy, SymPy and numba are loaded and the kernel compiled by then): its peak must
stay at most ``MEMORY_LIMIT_MB`` (200 MB) and its growth from the first tenth to the end at
most ``FLAT_LIMIT_MB`` (20 MB: a leak of two bytes per sample shows 18 MB over 9·10⁶
samples, while a chunk's result arrays, freed and reallocated, move the resident set by a few MB). θ̂ at the end must lie
within ``THETA_RTOL`` of θ. The exit code is 1 when a check fails.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from thetahat.estimation.observer.compiled import compile_observer
from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model

#: True parameter of the stream.
THETA = 1.0
#: Period of the input (s) and sampling step (s).
PERIOD, DT = 2.0, 1e-3
#: Limits of the soak (MB of resident memory above the pre-stream baseline).
MEMORY_LIMIT_MB = 200.0
FLAT_LIMIT_MB = 20.0
#: θ̂ at the end within 1 % of θ: the accuracy the examples aim for (the noise-free record's
#: remaining error is the zero-order-hold discretisation at dt = 1 ms).
THETA_RTOL = 0.01
#: Chunked and whole runs agree to rounding (z is rebuilt from φ̂ and g: a few ulps).
RESUME_ATOL = 1e-9
#: Checkpoints per stream.
CHECKPOINTS = 10


def rss_mb() -> float:
    """Resident set of this process in MB (0 where /proc is unavailable)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def peak_rss_mb() -> float:
    """Peak resident set of this process in MB (``getrusage``; 0 where unavailable)."""
    try:
        import resource
    except ImportError:
        return 0.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3     # Linux: kB


def one_period(spec) -> tuple[np.ndarray, np.ndarray]:
    """(u, y) over one period of the plant's periodic steady state, sampled at DT."""
    sysm = spec.system
    A, B, C, E = sysm.A, sysm.B, sysm.C, sysm.E
    g = sysm.perturbation

    def u_of(t: float) -> np.ndarray:
        w = 2 * np.pi / PERIOD
        return np.array([np.sin(w * t) + 0.5 * np.sin(3 * w * t)])

    def rhs(t: float, x: np.ndarray) -> np.ndarray:
        u = u_of(t)
        y = C @ x
        phi = g.g(np.concatenate((u, y)), x, np.array([THETA]))
        return A @ x + B @ u + E @ phi

    x = np.zeros(A.shape[0])
    for _ in range(40):                        # settle: 40 periods, far beyond the transients
        x = solve_ivp(rhs, (0.0, PERIOD), x, rtol=1e-10, atol=1e-12).y[:, -1]
    n = int(round(PERIOD / DT))
    t = np.arange(n) * DT
    sol = solve_ivp(rhs, (0.0, PERIOD), x, t_eval=t, rtol=1e-10, atol=1e-12)
    u = np.stack([u_of(s) for s in t])
    y = (C @ sol.y).T
    return u, y


def stream_step(comp, state, u, y, N: int) -> tuple[np.ndarray, list[float]]:
    period = u.shape[0]
    marks = {int(N * (i + 1) / CHECKPOINTS) for i in range(CHECKPOINTS)}
    mem = []
    for i in range(N):
        j = i % period
        state = comp.step(state, u[j], y[j], comp.dt)
        if i + 1 in marks:
            mem.append(rss_mb())
    return state, mem


def resume_state(obs, res, u_last: np.ndarray, y_last: np.ndarray) -> np.ndarray:
    """The observer state at the last sample of a ``run``: x̂, θ̂ and x̂₂ are in the result,
    z = φ̂ − g(v, x̂, θ̂) by (3c) (the example's law keeps no state of its own)."""
    x_hat, theta_hat = res.x_hat[-1], res.theta_hat[-1]
    g = obs.system.perturbation.g(np.concatenate((u_last, y_last)), x_hat, theta_hat)
    x2 = None if res.x_hat_refined is None else res.x_hat_refined[-1]
    return obs.init(x_hat0=x_hat, theta_hat0=theta_hat, z0=res.phi_hat[-1] - g,
                    x_hat_refined0=x2)


def stream_chunks(comp, obs, state, u, y, N: int, chunk: int) -> tuple[np.ndarray, list[float]]:
    """``run`` over chunks that share their end sample: chunk c covers samples a … a + size,
    its last state starts chunk c + 1."""
    period = u.shape[0]
    reps = -(-chunk // period) + 2
    U, Y = np.tile(u, (reps, 1)), np.tile(y, (reps, 1))
    mem, done, next_mark = [], 0, 1
    while done < N:
        size = min(chunk, N - done)
        offset = done % period
        t = np.arange(size + 1) * DT      # local time: the observer is time-invariant, and
        #                                   absolute t = 10⁴ s would blur the spacing check
        res = comp.run(t, U[offset:offset + size + 1], Y[offset:offset + size + 1],
                       state0=state)
        state = resume_state(obs, res, U[offset + size], Y[offset + size])
        done += size
        while next_mark <= CHECKPOINTS and done >= N * next_mark / CHECKPOINTS:
            mem.append(rss_mb())
            next_mark += 1
    return state, mem


def check_resumption(comp, obs, s0, u, y) -> float:
    """Largest |θ̂ difference| between one run over 3 periods and the same in chunks of 777."""
    n = 3 * u.shape[0]
    U, Y = np.tile(u, (3, 1)), np.tile(y, (3, 1))
    whole = comp.run(np.arange(n) * DT, U, Y, state0=s0).theta_hat[-1]
    state, _ = stream_chunks(comp, obs, s0, u, y, n - 1, 777)
    return float(np.max(np.abs(state[obs.layout.theta] - whole)))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=10_000_000)
    ap.add_argument("--chunk", type=int, default=100_000)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    spec = loads_model(EXAMPLE_MODEL)
    obs = build_observer(spec)
    comp = compile_observer(obs, dt=DT)
    u, y = one_period(spec)
    s0 = comp.init(theta_hat0=spec.estimator.theta_hat0)
    comp.step(s0, u[0], y[0], DT)                       # compile before measuring
    comp.run(np.arange(3) * DT, u[:3], y[:3], state0=s0)
    lay = obs.layout
    resumed = check_resumption(comp, obs, s0, u, y)
    print(f"chunked run vs one run over 3 periods: max |Δθ̂| = {resumed:.2e}")
    out: dict = {"samples": args.samples, "chunk": args.chunk, "theta": THETA,
                 "memory_limit_mb": MEMORY_LIMIT_MB, "flat_limit_mb": FLAT_LIMIT_MB,
                 "resumption_error": resumed}
    ok = resumed <= RESUME_ATOL
    for name in ("run_chunks", "step"):
        base = rss_mb()
        start = time.perf_counter()
        if name == "step":
            state, mem = stream_step(comp, s0, u, y, args.samples)
        else:
            state, mem = stream_chunks(comp, obs, s0, u, y, args.samples, args.chunk)
        wall = time.perf_counter() - start
        theta_hat = float(np.asarray(state)[lay.theta][0])
        growth = [m - base for m in mem]
        row = {"wall_s": wall, "us_per_sample": 1e6 * wall / args.samples,
               "baseline_mb": base, "peak_growth_mb": max(growth), "growth_mb": growth,
               "flat_mb": growth[-1] - growth[0], "theta_hat_end": theta_hat,
               "theta_rel_error": abs(theta_hat - THETA) / THETA}
        row["ok"] = (row["peak_growth_mb"] <= MEMORY_LIMIT_MB and row["flat_mb"] <= FLAT_LIMIT_MB
                     and row["theta_rel_error"] <= THETA_RTOL)
        ok &= row["ok"]
        out[name] = row
        print(f"{name:>10}: {args.samples:.3g} samples in {wall:.1f} s "
              f"({row['us_per_sample']:.2f} µs/sample); RSS {base:.0f} MB before, peak growth "
              f"{row['peak_growth_mb']:.1f} MB (limit {MEMORY_LIMIT_MB:g}), first tenth → end "
              f"{row['flat_mb']:+.1f} MB (limit {FLAT_LIMIT_MB:g}); θ̂ = {theta_hat:.6g} "
              f"(θ = {THETA:g}, error {row['theta_rel_error']:.2%}) {'ok' if row['ok'] else 'FAIL'}")
    out["ok"] = ok
    out["process_peak_rss_mb"] = peak_rss_mb()
    print(f"process peak resident set (interpreter, NumPy, SciPy, SymPy, numba and both "
          f"streams): {out['process_peak_rss_mb']:.0f} MB")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    sys.exit(0 if main()["ok"] else 1)
