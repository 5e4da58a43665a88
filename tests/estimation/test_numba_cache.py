"""Issue 37, numba's cache and the printed modules: no cache content may crash the process,
change a result or be loaded unverified (thetahat.estimation.kernels.numba_cache).

A child process compiles two small printed kernels through :func:`load_module` (two gradient laws,
θ̂' = γ φ (y − φ θ̂), over the same record; each kernel is a printed module whose function has
the same name, so one's numba files fit the other's names). Every case damages a copy of that
cache, then runs the child again and checks: exit 0, each θ̂ equal to the clean run's, at most
one ThetahatWarning line (and no other warning), and a third run that loads both kernels from
the cache with no warning (repaired).

θ̂ is compared exactly: a kernel loaded from numba's cache and one compiled again are the same
machine code from the same LLVM on the same machine (numba caches the object code it
compiled), run on the same inputs. The two laws give θ̂ differing by more than 1e-3
(checked), so swapped caches would show.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

ROOT = Path(__file__).resolve().parents[2]
#: A child imports numba and compiles at most two small kernels (~3 s unloaded).
CHILD_SECONDS = 300

RUN = r"""
import errno, json, os, sys, warnings
import numpy as np
from thetahat.errors import ThetahatWarning
import thetahat.estimation.kernels.kernel_cache as kc
from thetahat.estimation.kernels.kernel_cache import load_module

fault = sys.argv[1]
if fault in ("enospc", "erofs"):          # every write to the cache fails
    code = errno.ENOSPC if fault == "enospc" else errno.EROFS
    def refuse(*args, **kwargs):
        raise OSError(code, os.strerror(code))
    import numba.core.caching as caching
    caching.IndexDataCacheFile._open_for_write = refuse
    import thetahat.estimation.kernels.numba_cache as nc
    nc.write_text = refuse
    kc.write_text = refuse
if fault == "nocache":
    def no_cache():
        raise kc.FileAccessError("thetahat found no writable directory (test)")
    kc.cache_dir = no_cache

def law(gain):
    # θ̂' = gain φ (y − φ θ̂), a printed module's compiled ``run`` (the same name in both)
    source = ("'a test kernel'\nimport numba\n\n\n@numba.njit(nogil=True, cache=True)\n"
              "def run(phi, y):\n    theta = 0.0\n    for i in range(phi.shape[0]):\n"
              f"        theta += {gain!r} * phi[i] * (y[i] - phi[i] * theta)\n"
              "    return theta\n")
    return load_module(source, "thetahat_nbtest").run

t = np.linspace(0.0, 1.0, 201)    # short: the two laws have not converged
phi = np.sin(t) + 1.5
y = 2.0 * phi
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    f = law(0.01)
    g = law(0.005)
    theta = [f(phi, y), g(phi, y)]
print(json.dumps({
    "theta": theta,
    "modules": [f.py_func.__module__, g.py_func.__module__],
    "hits": [sum(d.stats.cache_hits.values()) for d in (f, g)],
    "mine": [str(w.message) for w in caught if issubclass(w.category, ThetahatWarning)],
    "other": [f"{w.category.__name__}: {w.message}" for w in caught
              if not issubclass(w.category, ThetahatWarning)],
}))
"""


def child(cache: Path, fault: str = "none") -> dict:
    """Run ``RUN`` (from a file beside the cache: numba prints kernels from their source) in a
    child process; its JSON, after asserting it exited 0."""
    script = cache.parent / "numba_cache_child.py"
    if not script.exists():
        script.write_text(RUN)
    env = {**os.environ, "THETAHAT_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    env.pop("NUMBA_CACHE_DIR", None)   # numba's files in __pycache__ beside the modules
    out = subprocess.run([sys.executable, str(script), fault], capture_output=True, text=True,
                         env=env, timeout=CHILD_SECONDS)
    assert out.returncode == 0, (f"the child exited {out.returncode} (negative: killed by "
                                 f"signal {-out.returncode}):\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> tuple[Path, dict]:
    """A cache holding both kernels, and the clean run's output."""
    cache = tmp_path_factory.mktemp("pristine")
    first = child(cache)
    assert first["mine"] == [] and first["other"] == [] and first["hits"] == [0, 0]
    again = child(cache)
    assert again["hits"] == [1, 1] and again["mine"] == [] and again["other"] == []
    assert again["theta"] == first["theta"]
    assert abs(first["theta"][0] - first["theta"][1]) > 1e-3
    return cache, first


def _files(cache: Path, module: str, suffix: str) -> list[Path]:
    return sorted((cache / "__pycache__").glob(f"{module}.*{suffix}"))


def _one(cache: Path, module: str, suffix: str) -> Path:
    (path,) = _files(cache, module, suffix)
    return path


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def randomize(path: Path) -> None:
    path.write_bytes(os.urandom(path.stat().st_size))


def empty(path: Path) -> None:
    path.write_bytes(b"")


def swap(cache: Path, f: str, g: str, suffix: str) -> None:
    """g's numba file copied over f's (f's manifest left as it was)."""
    shutil.copyfile(_one(cache, g, suffix), _one(cache, f, suffix))


def swap_all(cache: Path, f: str, g: str) -> None:
    """g's index and data copied under f's names (f's manifest left as it was)."""
    for suffix in (".nbi", ".nbc"):
        swap(cache, f, g, suffix)


def swap_forged(cache: Path, f: str, g: str) -> None:
    """g's index, data and manifest under f's names: a forged entry the manifest agrees with.
    numba's own key (the source's stamp, the bytecode's hash) then misses: it compiles."""
    swap_all(cache, f, g)
    text = (cache / "__pycache__" / f"{g}.thetahat-numba.json").read_text()
    (cache / "__pycache__" / f"{f}.thetahat-numba.json").write_text(text.replace(g, f))


def unrecorded(cache: Path, f: str) -> None:
    """A foreign data file beside f's, under a name numba would read next."""
    nbc = _one(cache, f, ".nbc")
    shutil.copyfile(nbc, nbc.with_name(nbc.name.replace(".1.nbc", ".2.nbc")))


def forged(cache: Path, f: str) -> None:
    """f's data file damaged and its manifest made to agree: numba's own load then fails."""
    import hashlib
    nbc = _one(cache, f, ".nbc")
    truncate(nbc)
    man_path = cache / "__pycache__" / f"{f}.thetahat-numba.json"
    man = json.loads(man_path.read_text())
    man["files"][nbc.name] = hashlib.sha256(nbc.read_bytes()).hexdigest()
    man_path.write_text(json.dumps(man))


def edit_module(cache: Path, f: str) -> None:
    path = cache / f"{f}.py"
    path.write_text(path.read_text().replace("theta", "theta_edited"))


def manifest_damaged(cache: Path, f: str) -> None:
    (cache / "__pycache__" / f"{f}.thetahat-numba.json").write_bytes(b"{\x00\xff")


def manifest_lost(cache: Path, f: str) -> None:
    """f's manifest deleted (as for a cache written before the manifests): its files are
    deleted unread, without a warning, and compiled again."""
    (cache / "__pycache__" / f"{f}.thetahat-numba.json").unlink()


def numba_files_lost(cache: Path, f: str) -> None:
    for path in _files(cache, f, ".nbi") + _files(cache, f, ".nbc"):
        path.unlink()


def modules_lost(cache: Path, f: str) -> None:
    for path in cache.glob("thetahat_nbtest_*.py"):
        path.unlink()


#: (case, damage of (cache, f, g), fault, the warning's words or None for no warning).
CASES = [
    ("index truncated", lambda c, f, g: truncate(_one(c, f, ".nbi")), "none", "did not record"),
    ("data truncated", lambda c, f, g: truncate(_one(c, f, ".nbc")), "none", "did not record"),
    ("index empty", lambda c, f, g: empty(_one(c, f, ".nbi")), "none", "did not record"),
    ("data empty", lambda c, f, g: empty(_one(c, f, ".nbc")), "none", "did not record"),
    ("index random", lambda c, f, g: randomize(_one(c, f, ".nbi")), "none", "did not record"),
    ("data random", lambda c, f, g: randomize(_one(c, f, ".nbc")), "none", "did not record"),
    ("other kernel's data", lambda c, f, g: swap(c, f, g, ".nbc"), "none", "did not record"),
    ("other kernel's index and data", swap_all, "none", "did not record"),
    ("other kernel's files and manifest", swap_forged, "none", None),
    ("an unrecorded data file", lambda c, f, g: unrecorded(c, f), "none", "did not record"),
    ("damaged manifest", lambda c, f, g: manifest_damaged(c, f), "none", "did not record"),
    ("damaged file its manifest agrees with", lambda c, f, g: forged(c, f), "none",
     "failed to load"),
    ("printed module edited", lambda c, f, g: edit_module(c, f), "none", "rewrote"),
    ("manifest lost", lambda c, f, g: manifest_lost(c, f), "none", None),
    ("numba files lost", lambda c, f, g: numba_files_lost(c, f), "none", None),
    ("full disk while numba stores", lambda c, f, g: numba_files_lost(c, f), "enospc",
     "No space left on device"),
    ("read-only cache, modules to write", lambda c, f, g: modules_lost(c, f), "erofs",
     "Read-only file system"),
    ("no writable cache folder at all", lambda c, f, g: None, "nocache", "no cache"),
]


#: Cases whose f files are still the recorded ones: numba may load them (the module's text is
#: the same, so is numba's key). In every other case f's machine code is compiled again.
F_KEPT = ("an unrecorded data file", "printed module edited")


@pytest.mark.parametrize("case,damage,fault,words", CASES, ids=[c[0] for c in CASES])
def test_damaged_cache_gives_the_clean_result(pristine, tmp_path, case, damage, fault, words):
    source, clean = pristine
    cache = tmp_path / "cache"
    shutil.copytree(source, cache, symlinks=True)
    f, g = clean["modules"]
    damage(cache, f, g)
    out = child(cache, fault)
    assert out["theta"] == clean["theta"]
    assert out["other"] == []
    assert len(out["mine"]) == (0 if words is None else 1), out["mine"]
    if words is not None:
        (line,) = out["mine"]
        assert words in line and "\n" not in line, line
    if fault == "none" and case not in F_KEPT:     # f compiled again, g loaded, checked
        assert out["hits"] == [0, 1], out["hits"]
    if fault != "none":                # the next process stores what could not be
        child(cache)
    last = child(cache)                # then a process loads it all, silently
    assert last["mine"] == [] and last["other"] == [] and last["hits"] == [1, 1]
    assert last["theta"] == clean["theta"]


def test_a_save_another_process_is_recording_is_not_deleted(tmp_path):
    """Two processes compiling one kernel at once (a fleet's workers): numba writes the files,
    then their process hashes them into the manifest. One whose guard ran in that window
    deleted the other's fresh files and warned "damaged or foreign" (a fleet row then differed
    from the in-process run's). The guard now waits up to RECORD_WAIT for a fresh file to be
    recorded; one that never is, is still deleted and counted."""
    import hashlib
    import threading
    import thetahat.estimation.kernels.numba_cache as nc
    module = "thetahat_test_race"
    saved = tmp_path / f"{module}.run-3.py311.nbi"
    saved.write_bytes(b"index being recorded")
    nc._write_manifest(tmp_path, module, {})
    sha = hashlib.sha256(saved.read_bytes()).hexdigest()
    late = threading.Timer(0.1, nc._write_manifest, (tmp_path, module, {saved.name: sha}))
    late.start()
    try:
        assert nc._purge_unrecorded(tmp_path, module) == 0
    finally:
        late.join()
    assert saved.exists()
    stray = tmp_path / f"{module}.run-3.py311.1.nbc"
    stray.write_bytes(b"never recorded")
    assert nc._purge_unrecorded(tmp_path, module) == 1
    assert saved.exists() and not stray.exists()


def test_two_processes_recording_at_once_keep_each_others_records(tmp_path):
    """Two processes saving different functions of one printed module at once (a fleet's
    workers compiling): each writes its files and records them, 150 times. Every record is a
    read-modify-write of the module's manifest; without the folder's lock the last write
    dropped the other process's files, which the next process then deleted as "damaged or
    foreign" (the fleet test failed so on a fresh cache). At the end both processes' files
    are in the manifest with their hashes."""
    import thetahat.estimation.kernels.numba_cache as nc
    module = "thetahat_test_writers"
    code = (
        "import sys\n"
        "from pathlib import Path\n"
        "import thetahat.estimation.kernels.numba_cache as nc\n"
        "folder, module, tag = Path(sys.argv[1]), sys.argv[2], sys.argv[3]\n"
        "base = f'{module}.f{tag}-3.py311.'\n"
        "for i in range(150):\n"
        "    (folder / (base + 'nbi')).write_bytes(f'index {tag} {i}'.encode())\n"
        "    (folder / (base + '0.nbc')).write_bytes(f'data {tag} {i}'.encode())\n"
        "    nc._record(folder, module, base)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path), module, tag],
                              env=env) for tag in "ab"]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    good, bad = nc._checked(tmp_path, module)
    assert bad == [] and len(good) == 4, (sorted(good), bad)
