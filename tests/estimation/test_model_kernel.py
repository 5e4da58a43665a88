"""Stage 2's model kernels: f against the system's parts, the RK4 map's Jacobians against
finite differences, the sub-step rule's spectral-radius bound, and the compiled path."""

from __future__ import annotations

import numpy as np
import pytest

from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.estimation.statistical.plant_kernel import (Propagation, model_kernel,
                                                          spectral_radius_bound)
from thetahat.models import lugre

#: Central differences with step 1e-6 (relative) of a smooth map: truncation ~1e-12 and
#: rounding ~1e-16/1e-6 = 1e-10 relative; 1e-6 leaves a wide margin.
FD_RTOL = 1e-6


@pytest.fixture(scope="module")
def kern():
    return model_kernel(lugre.system(), compiled=False)


def test_f_is_the_system_with_y_equal_to_C_x(kern):
    sys_ = lugre.system()
    rng = np.random.default_rng(0)
    for _ in range(5):
        x = rng.normal(size=2) * [2.0, 1e-3]
        u, th = rng.normal(size=1), [0.3]
        v = np.concatenate([u, sys_.C @ x])
        want = sys_.A @ x + sys_.B @ u + sys_.E @ sys_.perturbation.g(v, x, th)
        np.testing.assert_allclose(kern.f(x, u, th), want, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("x", [[1.5, 1e-3], [-0.4, -5e-4], [0.003, 2e-4]])
def test_rk4_map_jacobians_match_central_differences(kern, x):
    x = np.array(x)
    th, U = np.array([0.28]), np.array([[0.2], [0.25]])
    pc, WT = Propagation(hold="foh").arrays()
    Phi, Gam = np.empty((2, 2)), np.empty((2, 1))
    kern.propagate(x, th, U, 0, 1e-3, pc, WT, True, Phi, Gam)
    scratch = (np.empty((2, 2)), np.empty((2, 1)))

    def F(xx, tt):
        return kern.propagate(np.array(xx), np.array(tt), U, 0, 1e-3, pc, WT, False, *scratch)

    for j, h in enumerate(1e-6 * np.maximum(np.abs(x), [1e-3, 1e-6])):
        e = np.zeros(2)
        e[j] = h
        fd = (F(x + e, th) - F(x - e, th)) / (2 * h)
        np.testing.assert_allclose(Phi[:, j], fd, rtol=FD_RTOL, atol=FD_RTOL * np.abs(Phi).max())
    d = 1e-6 * th[0]
    fd = (F(x, th + d) - F(x, th - d)) / (2 * d)
    np.testing.assert_allclose(Gam[:, 0], fd, rtol=FD_RTOL, atol=FD_RTOL * np.abs(Gam).max())


@pytest.mark.parametrize("name", ["lugre", "two_inertia", "silverbox", "wheel"])
@pytest.mark.parametrize("hold", ["zoh", "foh", "bandlimited"])
def test_the_map_over_reused_work_arrays_is_the_map(name, hold):
    """propagate_into over one set of work arrays reused for every sample (filled with NaN
    first, and x_next written over x) gives what propagate gives with fresh arrays, bit for
    bit: Φ, Γ (all columns and none) and x over 30 samples of random inputs and a stiff
    interval (more sub-steps than the table holds, on the band-limited hold)."""
    from pathlib import Path

    from thetahat.modelfile import load_model

    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / f"{name}.toml")
    sys_ = spec.system
    kern = model_kernel(sys_, compiled=False)
    n, m, p = sys_.n, sys_.m, sys_.p
    rng = np.random.default_rng(3)
    U = rng.normal(size=(40, m))
    th = np.asarray(spec.scenario.theta, dtype=float)
    for pg in (p, 0):
        pc, WT = Propagation(hold=hold, substeps=2).arrays()
        pc2, WT2 = pc.copy(), WT.copy()
        work = kern.plant_work(n, p, pg, m, WT.shape[1])
        for a in work:
            a[...] = np.nan
        x = np.asarray(spec.scenario.x0, dtype=float).copy()
        y = x.copy()
        for k in range(30):
            h = 1e-3 * (1.0 + k % 3) if k != 7 else 0.5
            Phi, Gam = np.empty((n, n)), np.empty((n, pg))
            Phi2, Gam2 = np.empty((n, n)), np.empty((n, pg))
            want = kern.propagate(x, th, U, k, h, pc, WT, True, Phi, Gam)
            kern.propagate_into(y, y, th, U, k, h, pc2, WT2, True, Phi2, Gam2, *work)
            np.testing.assert_array_equal(y, want)
            np.testing.assert_array_equal(Phi2, Phi)
            np.testing.assert_array_equal(Gam2, Gam)
            if not np.all(np.isfinite(want)):
                break
            x = want


def test_spectral_radius_bound_is_an_upper_bound_and_tight_on_triangular_lugre():
    rng = np.random.default_rng(1)
    for _ in range(50):
        F = rng.normal(size=(4, 4)) * 10.0 ** rng.uniform(-3, 3, size=(4, 4))
        rho = np.max(np.abs(np.linalg.eigvals(F)))
        assert spectral_radius_bound(F) >= rho * (1 - 1e-12)
    F = np.array([[-76.5, 8.06e5], [0.0, -3523.0]])   # LuGre at high speed (measured)
    assert spectral_radius_bound(F) < 1.01 * 3523.0


def test_spectral_radius_bound_is_as_tight_as_lapacks_balancing():
    """The bound after Osborne's sweeps stopped at 5 % balance is within 1.5× the row-sum
    bound after LAPACK's balancing (scipy.linalg.matrix_balance: powers of 2, its own
    convergence test) on random matrices of sizes 2–6 whose entries span eight decades, and
    above the spectral radius. Measured worst 1.25× (2,000 matrices); 1.5× costs at most
    half as many sub-steps again, the bound's only use."""
    import scipy.linalg
    rng = np.random.default_rng(3)
    for n in range(2, 7):
        for _ in range(60):
            F = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-4, 4, size=(n, n))
            B = scipy.linalg.matrix_balance(F, permute=False, separate=False)[0]
            lapack = np.abs(B).sum(axis=1).max()
            bound = spectral_radius_bound(F)
            assert np.max(np.abs(np.linalg.eigvals(F))) * (1 - 1e-12) <= bound <= 1.5 * lapack


@pytest.mark.slow
def test_compiled_kernels_agree_with_the_numpy_fallback():
    pytest.importorskip("numba")
    data = lugre.simulate(seed=2, t_end=0.5)
    ekfs = [JointEKF(system=lugre.system(), compiled=c) for c in (False, True)]
    runs = [e.run(data.t, data.u, data.y, state0=e.init(theta_hat0=[1.0])) for e in ekfs]
    np.testing.assert_allclose(runs[1].theta_hat, runs[0].theta_hat, rtol=0, atol=1e-10)
    est = [lugre.estimator("guarded", compiled=c) for c in (False, True)]
    res = [e.run(data.t, data.u, data.y, state0=e.init(theta_hat0=[1.0])) for e in est]
    # stage 1 differs by rounding (compiled vs Python observer), stage 2 and the fits by
    # rounding; 1e-8 N m is 4e-8 of θ
    np.testing.assert_allclose(res[1].theta_hat, res[0].theta_hat, rtol=0, atol=1e-8)


def test_plain_python_kernels_overflow_to_inf_as_the_compiled_ones_do():
    """exp(θ x) beyond float range: Python's math raises, numba gives inf. The plain-Python
    kernels must give inf too, so that a free run that leaves float range ends with a
    non-finite status (which callers check) instead of an OverflowError mid-loop."""
    from thetahat.modelfile import loads_model

    spec = loads_model('[system]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\nE = [[1.0]]\n'
                       '[perturbation]\ng = "exp(theta*y) - 1"\nu = ["u"]\ny = ["y"]\n'
                       'x = ["x"]\ntheta = ["theta"]\n'
                       '[parameter_set]\nlower = [0.5]\nupper = [2.0]\n'
                       '[estimator]\nlaw = "algebraic"\n')
    kern = model_kernel(spec.system, compiled=False)
    f = kern.f(np.array([800.0]), np.zeros(1), np.array([2.0]))   # exp(1600) > 1.8e308
    assert np.isposinf(f[0])
    f_in_range = kern.f(np.array([1.0]), np.zeros(1), np.array([2.0]))
    np.testing.assert_allclose(f_in_range[0], -1.0 + np.exp(2.0) - 1.0, rtol=1e-14)


def _rhs_jac(source: str):
    import math

    import numba
    namespace: dict = {"math": math}
    exec(source, namespace)                   # the source printed from the model's formulas
    return numba.njit(namespace["rhs_jac"])


@pytest.mark.parametrize("name", ["lugre", "silverbox", "emps", "cstr", "two_inertia"])
def test_a_square_printed_as_a_product_is_numbas_power_to_the_bit(name, monkeypatch):
    """The printed f, ∂f/∂x, ∂f/∂θ write a symbol's square as (x*x) (a call numba's RK4 stage
    did not fold away): compiled, they give the bits of the same source printed with x**2
    (SymPy's own printing) at 200 random points around the example's scenario, so no
    estimate changes by it."""
    pytest.importorskip("numba")
    from pathlib import Path

    from thetahat.estimation.statistical import plant_forms
    from thetahat.estimation.statistical.common import theta_box
    from thetahat.modelfile import load_model

    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / f"{name}.toml")
    system = spec.system
    product = plant_forms.rhs_jac_source(system)
    with monkeypatch.context() as m:
        m.delattr(plant_forms._ExactPrinter, "_print_Pow")
        power = plant_forms.rhs_jac_source(system)
    assert product != power and "**2" in power       # the model has squares to print
    fn_prod, fn_pow = _rhs_jac(product), _rhs_jac(power)
    n, p, m_ = system.n, system.p, system.B.shape[1]
    lo, hi = theta_box(system)
    rng = np.random.default_rng(11)
    for _ in range(200):
        x = rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 1, n)
        u = rng.standard_normal(m_)
        th = lo + (hi - lo) * rng.uniform(size=p)
        out = []
        for fn in (fn_prod, fn_pow):
            f, Fx, Ft = np.empty(n), np.empty((n, n)), np.empty((n, p))
            fn(x, u, th, f, Fx, Ft)
            out.append(np.concatenate([f, Fx.ravel(), Ft.ravel()]))
        assert out[0].tobytes() == out[1].tobytes()
