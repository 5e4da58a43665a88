"""The core works with numpy, scipy and sympy alone: every optional extra is made unimportable.

The script runs in a fresh interpreter in which importing any optional package fails, as it
would in a venv without the extras, and exercises the core API end to end: Assumption 1, the
SCB, K(ε) (the paper's numbers), the observer on simulated data, a model file, and the clear
error that names the missing extra.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

#: Every optional dependency of pyproject's extras (and what they pull in that we might import).
OPTIONAL = ("matplotlib", "control", "slycot", "numba", "llvmlite", "tqdm", "filterpy",
            "dask", "distributed", "pandas", "pyarrow", "xarray")

SCRIPT = textwrap.dedent("""
    import importlib.abc, sys

    BLOCKED = set(sys.argv[1].split(","))

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"optional package {name} is absent (blocked by the test)")
            return None

    sys.meta_path.insert(0, Block())

    import numpy as np
    import thetahat as th
    from thetahat.models import lugre
    from thetahat.modelfile import EXAMPLE_MODEL, loads_model, run_estimator

    # the paper's DC motor (Sec. VIII): design on sigma1 = 0, K(1) = [6, -0.0041588, 6.0075]
    J, s0, s1, a2 = 0.0023, 260.0, 0.6, 0.176
    A = [[-(a2 + s1) / J, -s0 / J], [1, 0]]; E = [[s1 / J], [-1]]; C = [[1, 0]]
    A0 = [[-a2 / J, -s0 / J], [1, 0]]; E0 = [[0], [-1]]
    assert th.check_assumption_1(A, E, C).holds
    assert th.scb(*th.extended_system(A, E, C)).n_a == 1
    d = th.modified_high_gain(A0, E0, C, eps=1.0)
    np.testing.assert_allclose(d.K.ravel(), [6.0, -0.0041588, 6.0075], rtol=1e-4)
    assert th.apply_design(d, A, E, C).stable

    data = lugre.simulate(seed=0, t_end=1.0)
    obs = lugre.observer(eps=1.0)
    res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=[0.5]))
    assert np.all(np.isfinite(res.x_hat)) and np.all((res.theta_hat >= 0.05) & (res.theta_hat <= 1))

    spec = loads_model(EXAMPLE_MODEL)
    t = np.arange(0.0, 1.0, 0.01)
    out = run_estimator(spec, t, np.sin(t)[:, None], np.zeros((t.size, 1)), method="paper")
    assert out.theta_hat.shape == (100, 1)

    # the two-stage estimator and the bound fall back to numpy kernels without numba
    short = lugre.simulate(seed=0, t_end=0.2)
    est = lugre.estimator("guarded")
    g = est.run(short.t, short.u, short.y, state0=est.init(theta_hat0=[1.0]))
    assert np.all((g.theta_hat >= 0.05) & (g.theta_hat <= 1)) and abs(g.theta_hat[-1, 0] - 0.28) < 0.01
    b = th.crlb(lugre.system(), short.t, short.u, theta=[0.28], noise_std=0.02)
    assert np.isfinite(b.std[-1, 0])

    try:
        th.compile_observer(obs, dt=1e-3)
    except th.ThetahatError as exc:
        assert "speed" in str(exc), exc
    else:
        raise SystemExit("compile_observer worked without numba")

    leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
    assert not leaked, leaked
    print("core-only: ok")
""")


def test_core_api_without_any_optional_extra():
    proc = subprocess.run([sys.executable, "-c", SCRIPT, ",".join(OPTIONAL)],
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "core-only: ok" in proc.stdout
