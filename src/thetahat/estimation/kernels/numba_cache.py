"""numba's cache files of the printed modules: only the files this process's kind recorded load.

numba keeps a compiled function of a ``cache=True`` dispatcher in two kinds of file in its
cache folder (``__pycache__`` next to the printed module, or numba's user-wide folder when that
one is not writable): an index ``<module>.<function>-<line>.pyXY.nbi`` and data files
``….<n>.nbc``, both pickles — and unpickling is code execution. numba reads them without a
check: a truncated or random file is an "internal error" on every later run, and a file copied
under a cached name is loaded as it is.

So :func:`guard` keeps, per printed module and cache folder, a manifest
``<module>.thetahat-numba.json`` with the SHA-256 of each of the module's numba files, written
by the process right after numba saved them (a wrapper around the dispatcher's cache's
``save_overload``). Before the module's first call, every ``.nbi``/``.nbc`` file of the module
that the manifest does not list with its hash is deleted (never read as a pickle), and numba
compiles again (with a warning when the module has a manifest; without one the files are a
former version's, deleted silently). Should loading still fail (a wrapper around
``load_overload``), the module's files are deleted and numba compiles: a cache can cost a
compile, never a result or the process. A file numba cannot write (a full disk, a read-only folder) leaves the function
compiled in memory. Each case gives one :class:`~thetahat.errors.ThetahatWarning` line.

What it does not protect against is the same as for the C cache
(:mod:`thetahat.codegen.native_cache`): whoever can write the cache folder can write a
matching manifest.

What lives here: :func:`guard`, :data:`FORMAT`, the limits. What it may import: the errors and
:mod:`thetahat.safe_io`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import stat
import threading
import time
import types
import warnings
from pathlib import Path
from typing import Any, Iterator

from ...errors import ThetahatWarning
from ...safe_io import write_text

__all__ = ["FORMAT", "MAX_FILE_BYTES", "MAX_MANIFEST_BYTES", "guard", "manifest_path"]

#: The manifest's format: a manifest of another format lists nothing.
FORMAT = "thetahat-numba-cache/1"
#: Largest numba cache file hashed (a kernel's data file is 0.1–5 MB); larger is discarded.
MAX_FILE_BYTES = 256 * 2**20
#: Largest manifest read (one line per file: a few kB).
MAX_MANIFEST_BYTES = 2**20
#: An unrecorded file younger than this (s) may be another process's save not yet recorded.
FRESH_SECONDS = 10.0
#: How long (s) the manifest is read again for such a file before it is judged (the save-to-
#: record window is writing and hashing a few MB: milliseconds on an idle machine, more with
#: a fleet's workers compiling on every core. The fleet failures once blamed on a short wait
#: here were lost manifest updates, which :func:`_folder_lock` prevents).
RECORD_WAIT = 2.0

_HEX = re.compile(r"[0-9a-f]{64}")
_lock = threading.Lock()
#: (cache folder, module) -> {file name: SHA-256} of the files trusted in this process.
_trusted: dict[tuple[str, str], dict[str, str]] = {}
#: Warnings already given by the wrappers (one line per module and kind per process).
_warned: set[tuple[str, str]] = set()


def manifest_path(folder: str | Path, module: str) -> Path:
    """The manifest of ``module``'s numba files in the cache folder ``folder``.

    Parameters
    ----------
    folder : str or Path
    module : str

    Returns
    -------
    Path

    Examples
    --------
    >>> manifest_path("/tmp/c", "thetahat_kernel_ab").name
    'thetahat_kernel_ab.thetahat-numba.json'
    """
    return Path(folder) / f"{module}.thetahat-numba.json"


def _read(path: Path, limit: int) -> bytes | None:
    """The bytes of a regular file of at most ``limit`` bytes, else None (never blocks, never
    follows a link)."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > limit:
            return None
        chunks, left = [], limit + 1
        while left > 0:
            chunk = os.read(fd, min(left, 2**20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
        return data if len(data) <= limit else None
    except OSError:
        return None
    finally:
        os.close(fd)


def _sha(path: Path) -> str | None:
    data = _read(path, MAX_FILE_BYTES)
    return None if data is None else hashlib.sha256(data).hexdigest()


def _recorded(folder: Path, module: str) -> dict[str, str]:
    """The manifest's files and hashes (empty when it is missing, damaged or foreign)."""
    raw = _read(manifest_path(folder, module), MAX_MANIFEST_BYTES)
    try:
        man = json.loads(raw.decode("utf-8")) if raw is not None else None
    except (UnicodeDecodeError, ValueError):
        return {}
    if not (isinstance(man, dict) and man.get("format") == FORMAT
            and man.get("module") == module and isinstance(man.get("files"), dict)):
        return {}
    return {k: v for k, v in man["files"].items()
            if isinstance(k, str) and isinstance(v, str) and _HEX.fullmatch(v)}


def _files(folder: Path, prefix: str) -> list[Path]:
    """numba's cache files in ``folder`` whose names start with ``prefix``."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    return [folder / n for n in sorted(names)
            if n.startswith(prefix) and (n.endswith(".nbi") or n.endswith(".nbc"))]


@contextlib.contextmanager
def _folder_lock(folder: Path, module: str) -> Iterator[None]:
    """Hold the module's lock file in ``folder`` (``flock``, shared by every process that
    records there) for a read-modify-write of its manifest: two processes recording at once
    otherwise each write the manifest they read plus their own files, and the last write
    drops the other's (whose files the next process then deletes as unrecorded). Without
    ``fcntl`` (not POSIX) or a lock file that cannot be opened, the block runs unlocked."""
    try:
        import fcntl
    except ImportError:                     # pragma: no cover - not POSIX
        yield
        return
    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(folder / f"{module}.thetahat-numba.lock", flags, 0o600)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)                        # (releases the lock)


def _remove(path: Path) -> None:
    try:
        if path.is_dir() and not path.is_symlink():
            path.rmdir()
        else:
            path.unlink()
    except OSError:
        pass


def _write_manifest(folder: Path, module: str, files: dict[str, str]) -> None:
    text = json.dumps({"format": FORMAT, "module": module, "files": files}, indent=1,
                      sort_keys=True)
    write_text(manifest_path(folder, module), text)


def _checked(folder: Path, module: str) -> tuple[dict[str, str], list[Path]]:
    """The module's files the manifest lists with their hash (name → hash), and the others."""
    recorded = _recorded(folder, module)
    good: dict[str, str] = {}
    bad: list[Path] = []
    for path in _files(folder, module + "."):
        want = recorded.get(path.name)
        if want is not None and _sha(path) == want:
            good[path.name] = want
        else:
            bad.append(path)
    return good, bad


def _fresh(path: Path) -> bool:
    try:
        return time.time() - path.stat().st_mtime < FRESH_SECONDS
    except OSError:
        return False


def _purge_unrecorded(folder: Path, module: str) -> int:
    """Delete the module's numba files that the manifest does not list with their hash; the
    number deleted when the module has a manifest (without one, the files are those of a
    thetahat before this check, or of a process that stopped before recording: deleted
    without a word). Remembers the others as trusted.

    A file written in the last :data:`FRESH_SECONDS` may be another process's save that it is
    about to record (numba writes the files, then that process hashes them into the
    manifest): the manifest is read again for up to :data:`RECORD_WAIT` seconds before such a
    file is judged (two processes compiling one kernel at once, as a fleet's workers do, made
    one of them delete the other's fresh files as "damaged or foreign"). It waits without
    holding this process's lock, so that this process's own saves are recorded meanwhile."""
    had_manifest = os.path.lexists(manifest_path(folder, module))
    good, bad = _checked(folder, module)
    deadline = time.monotonic() + RECORD_WAIT
    while any(_fresh(p) for p in bad) and time.monotonic() < deadline:
        time.sleep(0.02)
        good, bad = _checked(folder, module)
    with _lock, _folder_lock(folder, module):
        good, bad = _checked(folder, module)    # (a record may have landed meanwhile)
        for path in bad:
            _remove(path)
        _trusted[(str(folder), module)] = good
    return len(bad) if had_manifest else 0


def _warn_once(module: str, kind: str, message: str) -> None:
    """Warn once per module and kind; a cache that cannot be written ("save", "store": a
    full disk, a read-only folder) is said once per process."""
    key = ("", kind) if kind in ("save", "store") else (module, kind)
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(message, ThetahatWarning, stacklevel=4)


def _record(folder: Path, module: str, base: str) -> None:
    """After numba saved a function's files: trust them (their hashes now) and write the
    manifest, under the folder's lock: every file of the module whose content is what the
    manifest (another process's records) or this process trusted says, and this function's
    files as they are now. A file another process rewrote since this one trusted it keeps
    the manifest's hash of it, not this process's stale one."""
    key = (str(folder), module)
    with _lock, _folder_lock(folder, module):
        trusted = _trusted.setdefault(key, {})
        recorded = _recorded(folder, module)
        own = {p.name for p in _files(folder, base)}
        alive: dict[str, str] = {}
        for path in _files(folder, module + "."):
            now = _sha(path)
            if now is not None and (path.name in own or recorded.get(path.name) == now
                                    or trusted.get(path.name) == now):
                alive[path.name] = now
        _trusted[key] = alive
        try:
            _write_manifest(folder, module, alive)
        except OSError as exc:
            _warn_once(module, "store", f"cannot record numba's cache of {module} in "
                       f"{folder} ({exc}); it is compiled again by the next process.")


def _forget(folder: Path, module: str) -> None:
    """Delete every numba file of the module and its manifest's entries."""
    with _lock, _folder_lock(folder, module):
        for path in _files(folder, module + "."):
            _remove(path)
        _trusted[(str(folder), module)] = {}
        try:
            _write_manifest(folder, module, {})
        except OSError:
            pass


def _wrap(cache: Any, folder: Path, module: str) -> None:
    """Route the dispatcher's cache's loads and saves through the checks above."""
    load, save = cache.load_overload, cache.save_overload
    base = cache._cache_file._index_name[: -len(".nbi")] + "."

    def load_overload(sig: Any, target_context: Any) -> Any:
        try:
            return load(sig, target_context)
        except Exception as exc:        # any failure of numba's loader
            _forget(folder, module)
            _warn_once(module, "load", f"numba's cache of {module} in {folder} failed to "
                       f"load ({type(exc).__name__}); its files were deleted and numba "
                       "compiles again.")
            return None

    def save_overload(sig: Any, data: Any) -> None:
        try:
            save(sig, data)
        except OSError as exc:
            _warn_once(module, "save", f"numba cannot store its cache of {module} in "
                       f"{folder} ({exc.strerror or exc}); the kernel runs compiled in memory "
                       "and is compiled again by the next process.")
            return
        _record(folder, module, base)

    cache.load_overload = load_overload
    cache.save_overload = save_overload


def guard(mod: types.ModuleType) -> str | None:
    """Check numba's cache files of the printed module ``mod`` before its first call.

    Deletes the module's numba files that its manifest does not list with their SHA-256, and
    wraps each ``cache=True`` dispatcher's cache so that what numba saves is recorded and a
    failed load is a compile (see the module docstring).

    Parameters
    ----------
    mod : module
        Just imported by :func:`~thetahat.estimation.kernels.kernel_cache.load_module`, not
        yet called.

    Returns
    -------
    str or None
        What was discarded (for the caller's one warning line), or None.

    Examples
    --------
    >>> import types
    >>> guard(types.ModuleType("thetahat_doc_empty")) is None
    True
    """
    module = mod.__name__
    folders: dict[str, Path] = {}
    for value in list(vars(mod).values()):
        func = getattr(value, "py_func", None)
        if getattr(func, "__module__", None) != module:
            continue                    # a dispatcher another printed module owns
        cache = getattr(value, "_cache", None)
        path = getattr(cache, "_cache_path", None)
        if path is None or not hasattr(cache, "_cache_file"):
            continue
        folder = folders.setdefault(path, Path(path))
        _wrap(cache, folder, module)
    dropped = 0
    for folder in folders.values():         # (each takes the lock only to delete and trust)
        dropped += _purge_unrecorded(folder, module)
    if not dropped:
        return None
    where = ", ".join(str(f) for f in folders.values())
    return (f"deleted {dropped} numba cache file(s) of {module} in {where} that thetahat did "
            "not record (damaged or foreign); numba compiles them again")
