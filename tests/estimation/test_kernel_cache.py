"""Stage-2 kernels through printed, disk-cached modules: same results, compiled once."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from thetahat.estimation.kernels.modules import KernelSourceError, cached_njit
from thetahat.estimation.statistical.plant_kernel import jit, model_kernel
from thetahat.models import lugre

numba = pytest.importorskip("numba")


def _affine(a, b, table):
    def inner(x):
        return a * x + b

    def outer(x, out):
        for i in range(out.shape[0]):
            out[i] = inner(x) + table[i]
        return math_floor_free(out)

    def math_floor_free(out):
        s = 0.0
        for v in out:
            s += v
        return s

    return outer


def test_a_closure_with_numbers_arrays_and_kernels_equals_its_python():
    """The printed module binds each free name to what the closure held (exact floats)."""
    table = np.array([0.1, -2.5e-300, np.pi])
    fn = _affine(1.0 / 3.0, -7, table)
    out_py, out_nb = np.empty(3), np.empty(3)
    s_py = fn(0.7, out_py)
    s_nb = cached_njit(fn)(0.7, out_nb)
    np.testing.assert_array_equal(out_nb, out_py)       # same operations, no reassociation
    assert s_nb == s_py


def test_what_cannot_be_written_out_falls_back_to_memory():
    lookup = {"k": 2.0}

    def uses_a_dict(x):
        return x * 2.0 if lookup else x

    with pytest.raises(KernelSourceError, match="dict"):
        cached_njit(uses_a_dict)
    assert jit(lambda x: 2.0 * x, True)(3.0) == 6.0       # a lambda: compiled in memory


def test_stage2_propagation_matches_the_python_kernels():
    """LuGre's RK4 map and its Jacobians, compiled through the cache vs plain Python: the
    same arithmetic up to numba's contraction of a·b + c (1e-12 relative, margin 1e3 over
    the 1e-15 seen)."""
    sys_ = lugre.system()
    fast, slow = model_kernel(sys_, compiled=True), model_kernel(sys_, compiled=False)
    x, th = np.array([0.8, 2e-4]), np.array([0.28])
    u0, u1 = np.array([1.0]), np.array([1.05])
    outs = []
    for k in (fast, slow):
        Phi, Gam = np.empty((2, 2)), np.empty((2, 1))
        xn = k.propagate(x, th, u0, u1, 1e-3, 2.0, True, Phi, Gam)
        outs.append((xn, Phi, Gam))
    for a, b in zip(*outs):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)


SCRIPT = """
import json, numpy as np
from thetahat.estimation.statistical.plant_kernel import model_kernel
from thetahat.models import lugre
k = model_kernel(lugre.system(), compiled=True)
Phi, Gam = np.empty((2, 2)), np.empty((2, 1))
k.propagate(np.array([0.8, 2e-4]), np.array([0.28]), np.array([1.0]), np.array([1.0]),
            1e-3, 2.0, True, Phi, Gam)
st = k.propagate.stats
print(json.dumps({"hits": sum(st.cache_hits.values()), "misses": sum(st.cache_misses.values())}))
"""


def test_a_second_process_loads_the_machine_code(tmp_path):
    """The point of the cache: the first process compiles, the next one only loads."""
    env = {**os.environ, "THETAHAT_CACHE_DIR": str(tmp_path), "OPENBLAS_NUM_THREADS": "1"}
    runs = [json.loads(subprocess.run([sys.executable, "-c", SCRIPT], env=env, check=True,
                                      capture_output=True, text=True).stdout.splitlines()[-1])
            for _ in range(2)]
    assert runs[0]["misses"] >= 1
    assert runs[1] == {"hits": 1, "misses": 0}


@pytest.mark.parametrize("compiled", [False, True])
def test_the_plant_model_is_one_printed_module_from_the_cache(compiled):
    """rhs_jac (printed by SymPy) and the RK4 kernels live in one module file written to the
    cache directory under its content hash and imported from there (no exec of a string),
    compiled or as plain Python."""
    import inspect

    from thetahat.estimation.kernels.kernel_cache import cache_dir
    kern = model_kernel(lugre.system(), compiled=compiled)
    fns = [getattr(f, "py_func", f) for f in (kern.rhs_jac, kern.propagate)]
    files = {inspect.getsourcefile(f) for f in fns}
    assert len(files) == 1
    (path,) = files
    assert os.path.dirname(path) == str(cache_dir())
    assert os.path.basename(path).startswith("thetahat_plant_")
    assert kern.source in open(path, encoding="utf-8").read()
