"""Issue 37 (hostile round 3), the native cache: no cache content may crash the process or
change a result (thetahat.codegen.native_cache).

Every case damages a cache that holds the libraries of prop1 (at two step lengths) and prop2,
then runs prop1's record through the C back end in a child process — so a SIGBUS or SIGILL is
a failed test, not a dead pytest worker — and checks: exit 0, the C ran (no fallback), θ̂
equal to a clean run's, at most one warning line, and a valid entry in the cache afterwards.

θ̂ is compared to SAME_RTOL = 1e-12: the same sources compiled by the same compiler with the
same flags run the same machine code (measured: bit-identical); the bound only leaves room
for a compiler that does not reproduce its output byte for byte. A foreign library (prop2's,
or prop1's at another dt) gives a θ̂ off by more than 1e-3 (checked below), so the bound
tells a rebuilt library from a wrong one.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thetahat.codegen.loader import find_compiler

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler (cc or $CC)")

ROOT = Path(__file__).resolve().parents[2]
SAME_RTOL = 1e-12
#: A foreign library's θ̂ differs from the right one by more than this (measured: ≥ 1e-2).
FOREIGN_DIFF = 1e-3
#: A child process imports thetahat, builds the observer and maybe compiles (~3 s unloaded).
CHILD_SECONDS = 300

RUN = r"""
import errno, json, sys, warnings
from pathlib import Path
import numpy as np
from thetahat.modelfile import build_observer, load_model
from thetahat.modelfile.study import simulate_model
from thetahat.codegen.native import NativeObserver
import thetahat.codegen.native_cache as nc
import thetahat.codegen.loader as loader

model, dt, fault = sys.argv[1], float(sys.argv[2]), sys.argv[3]
built = []
real_build = nc.build
def counting_build(code, directory, **kw):
    built.append(code.name)
    return real_build(code, directory, **kw)
nc.build = counting_build
if fault in ("enospc", "erofs"):
    code_ = errno.ENOSPC if fault == "enospc" else errno.EROFS
    def failing_write(fh, data):
        fh.write(data[: len(data) // 2])        # a part reaches the disk, then it is full
        raise OSError(code_, __import__("os").strerror(code_))
    nc._write_all = failing_write
if fault == "nocache":
    def no_cache():
        raise nc.FileAccessError("thetahat found no writable directory (test)")
    nc.cache_dir = no_cache
spec = load_model(Path(sys.argv[4]) / "examples" / f"{model}.toml")
run = simulate_model(spec, 3, t_end=1.0)
t = (run.t - run.t[0]) * (dt / (run.t[1] - run.t[0]))
obs = build_observer(spec)
def never():
    raise AssertionError("the fallback ran: the record should have run in C")
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    res = NativeObserver(obs, never).run(t, run.u, run.y)
mine = [str(w.message) for w in caught if issubclass(w.category, nc.ThetahatWarning)]
print(json.dumps({"theta": res.theta_hat[-1].tolist(), "warnings": mine, "built": built}))
"""


def child(cache: Path, model: str = "prop1", dt: float = 0.01, fault: str = "none",
          tmp: Path | None = None) -> dict:
    """Run ``RUN`` in a child process; its JSON, after asserting it exited 0."""
    env = {**os.environ, "THETAHAT_CACHE_DIR": str(cache), "THETAHAT_C": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    if tmp is not None:
        env["TMPDIR"] = str(tmp)
    out = subprocess.run([sys.executable, "-c", RUN, model, repr(dt), fault, str(ROOT)],
                         capture_output=True, text=True, env=env, timeout=CHILD_SECONDS)
    assert out.returncode == 0, (f"the child exited {out.returncode} (negative: killed by "
                                 f"signal {-out.returncode}):\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def entries(cache: Path) -> dict[str, dict]:
    """Manifest file name → manifest, of every entry in ``cache``."""
    return {p.name: json.loads(p.read_text()) for p in sorted(cache.glob("*.json"))}


def assert_valid_entries(cache: Path) -> None:
    """Every manifest names a library whose size and SHA-256 are the recorded ones."""
    mans = entries(cache)
    assert mans
    for man in mans.values():
        data = (cache / man["library"]).read_bytes()
        assert len(data) == man["size"] and hashlib.sha256(data).hexdigest() == man["sha256"]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    """A cache with prop1 at dt 0.01 and 0.02 and prop2 at 0.01, and each one's clean θ̂."""
    cache = tmp_path_factory.mktemp("pristine")
    refs, names = {}, {}
    for label, model, dt in (("prop1", "prop1", 0.01), ("prop1_dt2", "prop1", 0.02),
                             ("prop2", "prop2", 0.01)):
        before = set(entries(cache))
        out = child(cache, model, dt)
        assert out["warnings"] == [] and out["built"] == ["thetahat_observer"]
        refs[label] = np.array(out["theta"])
        (names[label],) = set(entries(cache)) - before
    again = child(cache)                                   # a cache hit: nothing built
    assert again["built"] == [] and again["warnings"] == []
    np.testing.assert_allclose(again["theta"], refs["prop1"], rtol=SAME_RTOL, atol=0)
    for other in ("prop1_dt2", "prop2"):                  # the foreign libraries differ
        assert np.max(np.abs(refs[other] - refs["prop1"])) > FOREIGN_DIFF
    NAMES.update(names)
    return cache, refs


#: Label → manifest file name of the pristine entries.
NAMES: dict[str, str] = {}


def _lib(cache: Path, label: str) -> Path:
    return cache / entries(cache)[NAMES[label]]["library"]


def _manifest(cache: Path, label: str) -> Path:
    return cache / NAMES[label]


def truncate(cache: Path, size: int) -> None:
    lib = _lib(cache, "prop1")
    lib.write_bytes(lib.read_bytes()[:size])


def flip(cache: Path, where: float) -> None:
    lib = _lib(cache, "prop1")
    data = bytearray(lib.read_bytes())
    at = int(len(data) * where)
    data[at:at + 64] = bytes(b ^ 0xFF for b in data[at:at + 64])
    lib.write_bytes(bytes(data))


def foreign_library(cache: Path, label: str) -> None:
    """Another library copied over prop1's (the manifest left as it was)."""
    shutil.copyfile(_lib(cache, label), _lib(cache, "prop1"))


def foreign_entry(cache: Path, label: str) -> None:
    """Another entry (manifest and library) copied under prop1's names."""
    man = _manifest(cache, "prop1")
    mine = json.loads(man.read_text())
    theirs = json.loads(_manifest(cache, label).read_text())
    shutil.copyfile(cache / theirs["library"], cache / mine["library"])
    theirs["library"] = mine["library"]
    man.write_text(json.dumps(theirs))


def damaged_manifest(cache: Path) -> None:
    man = _manifest(cache, "prop1")
    man.write_bytes(man.read_bytes()[:40] + b"\x00\xff" + man.read_bytes()[42:])


def fifo_library(cache: Path) -> None:
    lib = _lib(cache, "prop1")
    lib.unlink()
    os.mkfifo(lib)


def directory_library(cache: Path) -> None:
    lib = _lib(cache, "prop1")
    lib.unlink()
    lib.mkdir()


def manifest_to_device(cache: Path) -> None:
    man = _manifest(cache, "prop1")
    man.unlink()
    man.symlink_to("/dev/zero")


def huge_manifest(cache: Path) -> None:
    _manifest(cache, "prop1").write_bytes(b"{" + b" " * 10_000_000 + b"}")


def lost_manifest(cache: Path) -> None:
    _manifest(cache, "prop1").unlink()


def lost_library(cache: Path) -> None:
    _lib(cache, "prop1").unlink()


#: (case, damage, fault, the warning's words or None for no warning).
CASES = [
    ("truncated to 8000 bytes", lambda c: truncate(c, 8000), "none", "truncated"),
    ("truncated to 100 bytes", lambda c: truncate(c, 100), "none", "truncated"),
    ("truncated to 0 bytes", lambda c: truncate(c, 0), "none", "truncated"),
    ("bytes flipped in the code", lambda c: flip(c, 0.3), "none", "SHA-256 differs"),
    ("bytes flipped in the header", lambda c: flip(c, 0.0), "none", "SHA-256 differs"),
    ("prop2's library under the name", lambda c: foreign_library(c, "prop2"), "none",
     "SHA-256 differs"),
    ("the dt-0.02 library under the name", lambda c: foreign_library(c, "prop1_dt2"), "none",
     "SHA-256 differs"),
    ("prop2's entry under the names", lambda c: foreign_entry(c, "prop2"), "none",
     "foreign entry, built for another model"),
    ("the dt-0.02 entry under the names", lambda c: foreign_entry(c, "prop1_dt2"), "none",
     "foreign entry, built for another model"),
    ("damaged manifest", damaged_manifest, "none", "not valid JSON"),
    ("10 MB manifest", huge_manifest, "none", "more than 65536"),
    ("manifest a link to /dev/zero", manifest_to_device, "none", "cannot be opened"),
    ("library a FIFO", fifo_library, "none", "not a regular file"),
    ("library a directory", directory_library, "none", "not a regular file"),
    ("library missing", lost_library, "none", "library is missing"),
    ("manifest missing", lost_manifest, "none", None),
    ("full disk while storing", lost_manifest, "enospc", "No space left on device"),
    ("read-only cache while storing", lost_manifest, "erofs", "Read-only file system"),
    ("no writable cache folder at all", lambda c: None, "nocache", "no cache for the C library"),
]


@pytest.mark.parametrize("damage,fault,words", [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_damaged_cache_gives_the_clean_result(pristine, tmp_path, damage, fault, words):
    source, refs = pristine
    cache = tmp_path / "cache"
    shutil.copytree(source, cache, symlinks=True)
    damage(cache)
    out = child(cache, fault=fault, tmp=tmp_path)
    np.testing.assert_allclose(out["theta"], refs["prop1"], rtol=SAME_RTOL, atol=0)
    assert len(out["warnings"]) == (0 if words is None else 1), out["warnings"]
    if words is not None:
        (line,) = out["warnings"]
        assert words in line and "\n" not in line, line
    if fault == "none":          # rebuilt and stored: the next process loads it, checked
        assert out["built"] == ["thetahat_observer"]
        assert_valid_entries(cache)
    elif fault in ("enospc", "erofs"):     # nothing half-written left behind
        assert not [p for p in cache.iterdir() if p.name.startswith(".thetahat-")]
        assert_valid_entries(cache)        # the other entries are untouched


def test_a_full_disk_is_recovered_from_by_the_next_process(pristine, tmp_path):
    """After a run that could not store its library, the next run builds and stores it."""
    source, refs = pristine
    cache = tmp_path / "cache"
    shutil.copytree(source, cache, symlinks=True)
    lost_manifest(cache)
    child(cache, fault="enospc", tmp=tmp_path)
    out = child(cache, tmp=tmp_path)
    assert out["warnings"] == [] and out["built"] == ["thetahat_observer"]
    out = child(cache, tmp=tmp_path)
    assert out["warnings"] == [] and out["built"] == []
    np.testing.assert_allclose(out["theta"], refs["prop1"], rtol=SAME_RTOL, atol=0)


# --- the ELF check alone (no library is loaded) -----------------------------------------------

@pytest.fixture(scope="module")
def library_bytes(tmp_path_factory) -> bytes:
    from thetahat.codegen import generate_c
    from thetahat.codegen.loader import build
    from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    return build(code, tmp_path_factory.mktemp("elf")).read_bytes()


def test_elf_check_accepts_a_built_library(library_bytes):
    from thetahat.codegen.native_cache import elf_problem
    assert elf_problem(library_bytes) is None


@pytest.mark.parametrize("cut", (0, 3, 40, 63, 64, 1000, 0.5, 0.9, 0.99, -1))
def test_elf_check_refuses_every_truncation(library_bytes, cut):
    """Cut anywhere, the file fails the check: its section table is its last part."""
    from thetahat.codegen.native_cache import elf_problem
    n = len(library_bytes)
    keep = cut if isinstance(cut, int) and cut >= 0 else (n - 1 if cut == -1 else int(n * cut))
    problem = elf_problem(library_bytes[:keep])
    assert problem is not None and ("truncated" in problem or "ELF" in problem), problem


@pytest.mark.parametrize("offset,value,words", [
    (4, 1, "word size"),                 # EI_CLASS: 32-bit
    (5, 2, "byte order"),                # EI_DATA: big-endian
    (16, 2, "not a shared object"),      # e_type: ET_EXEC
    (18, 40, "ELF machine 40"),          # e_machine: ARM
])
def test_elf_check_refuses_another_kind_of_file(library_bytes, offset, value, words):
    from thetahat.codegen.native_cache import elf_problem
    data = bytearray(library_bytes)
    data[offset] = value
    problem = elf_problem(bytes(data))
    assert problem is not None and words in problem, problem


def test_without_memory_files_the_checked_bytes_load_from_a_private_copy(library_bytes,
                                                                          monkeypatch):
    """On a system without memfd_create the checked bytes are written (atomically, like every
    file thetahat writes) to a private copy and loaded from there: the copy holds exactly
    those bytes, and the library's step symbol is there."""
    import types
    import thetahat.codegen.native_cache as nc
    monkeypatch.delattr(os, "memfd_create", raising=False)
    key = types.SimpleNamespace(name="prop3",
                                library_name=lambda sha: f"thetahat_c_prop3_test_{sha[:16]}.so")
    lib = nc._load(library_bytes, key)
    assert hasattr(lib, "prop3_step")
    copy = Path(lib._name)
    assert copy.read_bytes() == library_bytes
    assert not [p for p in copy.parent.iterdir() if p.name.startswith(".thetahat-")]
