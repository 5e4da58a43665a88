"""The cache of compiled C observers: verified before it is loaded, never trusted.

A shared library is machine code: loading a damaged one can kill the process (a truncated
``.so`` faults with SIGBUS when the loader maps pages the file does not have), and loading
another model's library under this model's name computes another model's θ̂ without a word.
So nothing in the cache directory is loaded on its name alone. Each entry is two files in
:func:`~thetahat.estimation.kernels.kernel_cache.cache_dir`:

``thetahat_c_<name>_<key>_<sha>.so``
    The library, named by 24 hex digits of its key and 16 of its own SHA-256 (a library is
    never rewritten in place: a rebuild has another name).
``thetahat_c_<name>_<key>.json``
    Its manifest (written after the library, atomically, by the process that built and probed
    it): the full key and what it is made of — the sources' SHA-256 (the generated C, which
    holds every number of the model and its hash, and the record-loop shim), the compiler's
    path, version and target, the flags, the machine and thetahat's version — and the
    library's file name, size and SHA-256.

:func:`cached_library` reads the manifest (a regular file of at most
:data:`MAX_MANIFEST_BYTES`, opened without blocking), checks that its key is this code's,
reads the library's bytes (a regular file of exactly the recorded size, at most
:data:`MAX_LIBRARY_BYTES`), checks their SHA-256 and their ELF header (a shared object of this
interpreter's class, byte order and machine, every loadable segment and the section table
inside the file), and only then loads *those bytes* — from an anonymous in-memory file
(``memfd_create``) where the system has one, so a file changed between the check and the load
cannot be what is loaded. An entry that fails any check is removed and rebuilt, with one
:class:`~thetahat.errors.ThetahatWarning` line that says what was wrong.

A library is built in a private temporary directory, checked the same way, and loaded once in
a child process (``python -I -S``: about 35 ms against about 550 ms for the compile, measured
on the development machine) before the parent loads it or the cache records it: a library
that crashes on loading crashes the child, and the parent falls back to another back end. A
cached library is not probed again: its bytes, checked against the manifest's SHA-256, are
the bytes that were probed. When the cache cannot be written (a read-only folder, a full
disk) the library is loaded from memory this time, with one warning line, and built again by
the next process.

What this protects against: damage (truncation, flipped bytes, a half-written file, a disk
that filled up) and mix-ups (another model's, compiler's or version's library under this
name). What it does not: someone who can write the cache directory can also write a matching
manifest, as they could replace the Python files thetahat runs; keep the cache directory as
private as the installation (``THETAHAT_CACHE_DIR``).

What lives here: :func:`cached_library`, :func:`library_key` (:class:`LibraryKey`),
:func:`elf_problem` and the limits. What it may import: the loader and generator of this
package, the kernel cache's directory, :mod:`thetahat.safe_io` and the errors.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import platform
import re
import stat
import struct
import subprocess
import sys
import tempfile
import threading
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from .._version import __version__
from ..errors import CCompilerError, FileAccessError, ThetahatWarning
from ..estimation.kernels.kernel_cache import cache_dir
from ..safe_io import atomic_path
from .generate import CCode
from .harness import C_FLAGS
from .loader import build, find_compiler, shim_source

__all__ = ["FORMAT", "MAX_LIBRARY_BYTES", "MAX_MANIFEST_BYTES", "LibraryKey", "cached_library",
           "elf_problem", "library_key"]

#: The manifest's format: a manifest of another format is not this cache's and is discarded.
FORMAT = "thetahat-native-cache/1"
#: Largest library read from the cache (the generated observers are 16–100 kB).
MAX_LIBRARY_BYTES = 64 * 2**20
#: Largest manifest read from the cache (a manifest is about 1 kB).
MAX_MANIFEST_BYTES = 64 * 2**10
#: Seconds the child process that loads a fresh library may take (it takes ~35 ms).
PROBE_SECONDS = 60.0

_HEX = re.compile(r"[0-9a-f]{64}")
_lock = threading.Lock()
#: Libraries loaded in this process, by key (one load per library: the loader never unloads).
_loaded: dict[str, ctypes.CDLL] = {}
#: Memory files holding loaded libraries: kept open while the process lives (the loader knows
#: a library by its path, /proc/self/fd/N, and a reused N would name the old library).
_memory_files: list[int] = []
_compilers: dict[tuple[str, int, int], tuple[str, str]] = {}


@dataclass(frozen=True, slots=True)
class LibraryKey:
    """What a cached library must have been built from to be loaded for a :class:`CCode`.

    Attributes
    ----------
    name : str
        The C prefix.
    key : str
        SHA-256 (64 hex digits) of every field below.
    sources : str
        SHA-256 of the generated header, source and hold, and of the record-loop shim.
    compiler, compiler_version : str
        The compiler's resolved path and its ``--version`` and ``-dumpmachine`` lines.
    flags : tuple of str
    machine : str
        The machine this interpreter runs on (``platform.machine()``).
    version : str
        thetahat's version.
    """

    name: str
    key: str
    sources: str
    compiler: str
    compiler_version: str
    flags: tuple[str, ...]
    machine: str
    version: str

    @property
    def manifest_name(self) -> str:
        """The manifest's file name in the cache."""
        return f"thetahat_c_{self.name}_{self.key[:24]}.json"

    def library_name(self, sha256: str) -> str:
        """The file name of a library of this key with content hash ``sha256``."""
        return f"thetahat_c_{self.name}_{self.key[:24]}_{sha256[:16]}.so"

    def fields(self) -> dict[str, Any]:
        """The manifest's fields that identify the key."""
        return {"format": FORMAT, "key": self.key, "name": self.name, "sources": self.sources,
                "compiler": self.compiler, "compiler_version": self.compiler_version,
                "flags": list(self.flags), "machine": self.machine, "thetahat": self.version}


def _compiler_identity(cc: str) -> tuple[str, str]:
    """The compiler's resolved path and its version and target lines (once per binary)."""
    path = os.path.realpath(cc)
    try:
        st = os.stat(path)
        ident = (path, st.st_mtime_ns, st.st_size)
    except OSError:
        ident = (path, 0, 0)
    if ident not in _compilers:
        lines = []
        for arg in ("--version", "-dumpmachine"):
            try:
                out = subprocess.run([cc, arg], capture_output=True, text=True, timeout=60)
                lines.append((out.stdout.strip().splitlines() or [""])[0])
            except (OSError, subprocess.SubprocessError):
                lines.append("")
        _compilers[ident] = (path, " | ".join(lines))
    return _compilers[ident]


def library_key(code: CCode, cc: str, flags: Sequence[str] = C_FLAGS) -> LibraryKey:
    """The key of ``code``'s library built by compiler ``cc`` with ``flags``.

    Parameters
    ----------
    code : CCode
    cc : str
        The compiler (:func:`~thetahat.codegen.loader.find_compiler`).
    flags : sequence of str

    Returns
    -------
    LibraryKey

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> from thetahat.codegen import generate_c
    >>> from thetahat.codegen.loader import find_compiler
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> cc = find_compiler()
    >>> cc is None or len(library_key(code, cc).key) == 64
    True
    """
    src = hashlib.sha256()
    for part in (code.name, code.real, code.hold, code.header, code.source, shim_source(code)):
        src.update(part.encode())
        src.update(b"\0")
    path, version = _compiler_identity(cc)
    fields = (src.hexdigest(), path, version, "\0".join(flags), platform.machine(), __version__)
    h = hashlib.sha256(FORMAT.encode())
    for part in (code.name, *fields):
        h.update(b"\0" + part.encode())
    return LibraryKey(name=code.name, key=h.hexdigest(), sources=src.hexdigest(), compiler=path,
                      compiler_version=version, flags=tuple(flags), machine=platform.machine(),
                      version=__version__)


# --------------------------------------------------------------------------------------------
# ELF: the header of this interpreter and of a library
# --------------------------------------------------------------------------------------------

def _interpreter_elf() -> tuple[int, int, int] | None:
    """(class, byte order, machine) of this interpreter's ELF header; None when not ELF."""
    try:
        with open(sys.executable or "/proc/self/exe", "rb") as fh:
            head = fh.read(20)
    except OSError:
        return None
    if len(head) < 20 or head[:4] != b"\x7fELF":
        return None
    order = "<" if head[5] == 1 else ">"
    return head[4], head[5], struct.unpack_from(order + "H", head, 18)[0]


def elf_problem(data: bytes) -> str | None:
    """What makes ``data`` not a shared library this process can load, or None.

    Checked: the ELF magic, a shared object (``ET_DYN``) of this interpreter's class (32/64
    bit), byte order and machine; the program header table, every loadable segment and the
    section header table inside the file (a truncated library fails here: the loader would map
    pages beyond the end of the file, and touching them is SIGBUS). On a system whose
    interpreter is not ELF (macOS, Windows) nothing is checked.

    Parameters
    ----------
    data : bytes
        The library's content.

    Returns
    -------
    str or None
        The problem in a few words.

    Examples
    --------
    >>> elf_problem(b"not a library") in ("not an ELF file (no ELF magic)", None)
    True
    """
    own = _interpreter_elf()
    if own is None:
        return None
    cls, order_byte, machine = own
    if data[:4] != b"\x7fELF":
        return "not an ELF file (no ELF magic)"
    wide = cls == 2
    head_fmt, ph_fmt = (("16sHHIQQQIHHHHHH", "IIQQQQQQ") if wide
                        else ("16sHHIIIIIHHHHHH", "IIIIIIII"))
    order = "<" if order_byte == 1 else ">"
    if len(data) < struct.calcsize(order + head_fmt):
        return f"truncated: {len(data)} bytes, shorter than an ELF header"
    if data[4] != cls or data[5] != order_byte:
        return "an ELF file of another word size or byte order than this interpreter's"
    (_, e_type, e_machine, _, _, phoff, shoff, _, _, phentsize, phnum, shentsize, shnum,
     _) = struct.unpack_from(order + head_fmt, data, 0)
    if e_type != 3:
        return f"an ELF file of type {e_type}, not a shared object"
    if e_machine != machine:
        return f"built for ELF machine {e_machine}, not this one's ({machine})"
    size = len(data)
    if phnum == 0 or phentsize < struct.calcsize(order + ph_fmt) or phoff + phnum * phentsize > size:
        return "truncated or damaged: its program header table is not inside the file"
    if shoff and shoff + shnum * shentsize > size:
        return f"truncated: {size} bytes, its section table ends at {shoff + shnum * shentsize}"
    for i in range(phnum):
        fields = struct.unpack_from(order + ph_fmt, data, phoff + i * phentsize)
        p_type = fields[0]
        offset, filesz, memsz = ((fields[2], fields[5], fields[6]) if wide
                                 else (fields[1], fields[4], fields[5]))
        if p_type == 1 and (offset + filesz > size or filesz > memsz):      # PT_LOAD
            return (f"truncated: {size} bytes, a loadable segment ends at byte "
                    f"{offset + filesz}")
    return None


# --------------------------------------------------------------------------------------------
# Reading, checking, writing and loading entries
# --------------------------------------------------------------------------------------------

class _Refused(Exception):
    """A cache entry that must not be loaded (the message says why)."""


def _read_bounded(path: Path, limit: int, what: str) -> bytes | None:
    """The bytes of the regular file ``path`` (None when absent), refusing anything else:
    opened without blocking and without following a last symlink, checked with ``fstat``."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)
                     | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise _Refused(f"its {what} cannot be opened ({exc.strerror or exc})") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _Refused(f"its {what} is not a regular file")
        if st.st_size > limit:
            raise _Refused(f"its {what} has {st.st_size} bytes, more than {limit}")
        os.set_blocking(fd, True)
        chunks, size = [], 0
        while size <= limit:
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        data = b"".join(chunks)
    except OSError as exc:
        raise _Refused(f"its {what} cannot be read ({exc.strerror or exc})") from exc
    finally:
        os.close(fd)
    if len(data) > limit:
        raise _Refused(f"its {what} grew beyond {limit} bytes while read")
    return data


#: The key's parts, as a refusal names them.
_WHAT = {"name": "C name", "sources": "model or generated code", "compiler": "compiler",
         "compiler_version": "compiler version", "flags": "set of compiler flags",
         "machine": "machine", "thetahat": "thetahat version"}


def _manifest(raw: bytes, key: LibraryKey) -> dict[str, Any]:
    """The manifest, checked to be this key's (else :class:`_Refused`)."""
    try:
        man = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise _Refused("its manifest is not valid JSON (damaged)") from exc
    if not isinstance(man, dict) or man.get("format") != FORMAT:
        raise _Refused("its manifest is not one of this cache's")
    if man.get("key") != key.key:
        what = [_WHAT[f] for f, v in key.fields().items() if f in _WHAT and man.get(f) != v]
        raise _Refused("it is a foreign entry, built for another "
                       + (" and ".join(what) or "key"))
    sha, size, lib = man.get("sha256"), man.get("size"), man.get("library")
    if not (isinstance(sha, str) and _HEX.fullmatch(sha) and type(size) is int
            and 0 < size <= MAX_LIBRARY_BYTES and lib == key.library_name(sha)):
        raise _Refused("its manifest lacks a valid library name, size or checksum")
    return man


def _verified(folder: Path, key: LibraryKey) -> bytes | None:
    """The cached library's bytes, checked (None when there is no entry)."""
    raw = _read_bounded(folder / key.manifest_name, MAX_MANIFEST_BYTES, "manifest")
    if raw is None:
        return None
    man = _manifest(raw, key)
    data = _read_bounded(folder / man["library"], MAX_LIBRARY_BYTES, "library")
    if data is None:
        raise _Refused("its library is missing")
    if len(data) != man["size"]:
        raise _Refused(f"its library has {len(data)} bytes, the manifest says {man['size']} "
                       "(truncated or changed)")
    if hashlib.sha256(data).hexdigest() != man["sha256"]:
        raise _Refused("its library's SHA-256 differs from the manifest's (changed or "
                       "replaced)")
    problem = elf_problem(data)
    if problem is not None:
        raise _Refused(f"its library is {problem}")
    return data


def _discard(folder: Path, key: LibraryKey) -> None:
    """Remove a refused entry: its manifest and every library of its key."""
    stem = f"thetahat_c_{key.name}_{key.key[:24]}"
    for path in [folder / key.manifest_name, *folder.glob(stem + "_*.so")]:
        try:
            if not path.is_dir():
                path.unlink()
        except OSError:
            pass


def _write_all(fh: IO[bytes], data: bytes) -> None:
    """Write ``data`` to ``fh`` (the one write of a cache entry's files)."""
    fh.write(data)


def _store(folder: Path, key: LibraryKey, data: bytes) -> None:
    """The library, then its manifest, each written atomically (the manifest last: an entry
    is complete when its manifest exists)."""
    sha = hashlib.sha256(data).hexdigest()
    man = {**key.fields(), "library": key.library_name(sha), "sha256": sha, "size": len(data)}
    for name, content in ((key.library_name(sha), data),
                          (key.manifest_name, json.dumps(man, indent=1).encode())):
        with atomic_path(folder / name) as tmp:
            with open(tmp, "wb") as fh:
                _write_all(fh, content)


_PROBE = ("import ctypes, sys\n"
          "lib = ctypes.CDLL(sys.argv[1])\n"
          "for symbol in sys.argv[3:]:\n"
          "    getattr(lib, symbol)\n"
          "state = ctypes.create_string_buffer(int(sys.argv[2]))\n"
          "sys.exit(0 if lib[sys.argv[3]](state, None, None) == 0 else 5)\n")


def _probe(path: Path, code: CCode) -> None:
    """Load the library at ``path`` in a child process and call ``<name>_init``; a crash or a
    failure there raises :class:`~thetahat.errors.CCompilerError`."""
    if not sys.executable:
        return
    P = code.name
    symbols = [f"{P}_init", f"{P}_step", f"{P}_phi_hat", f"{P}_run_record", f"{P}_run_steps"]
    try:
        out = subprocess.run([sys.executable, "-I", "-S", "-c", _PROBE, str(path),
                              str(max(code.state_bytes, 8)), *symbols],
                             capture_output=True, text=True, timeout=PROBE_SECONDS)
    except (OSError, subprocess.SubprocessError) as exc:
        raise CCompilerError(f"the C library built from {P}.c could not be test-loaded in a "
                             f"child process: {exc}") from exc
    if out.returncode != 0:
        how = (f"signal {-out.returncode}" if out.returncode < 0
               else f"exit {out.returncode}: {out.stderr.strip()[-300:]}")
        raise CCompilerError(f"the C library built from {P}.c failed to load in a child "
                             f"process ({how}); it is not used (another back end runs).")


def _build(code: CCode, folder: Path | None) -> bytes:
    """Compile ``code`` in a private temporary directory (the system's, else one in the cache
    folder); the library's bytes, checked and probed."""
    failures = []
    for parent in (None, folder) if folder is not None else (None,):
        try:
            with tempfile.TemporaryDirectory(prefix="thetahat-c-", dir=parent) as tmp:
                lib = build(code, tmp)
                data = lib.read_bytes()
                problem = elf_problem(data)
                if problem is not None:
                    raise CCompilerError(f"the compiler made a library that is {problem}.")
                _probe(lib, code)
                return data
        except OSError as exc:          # no room or no permission in that temporary folder
            failures.append(str(exc))
    raise CCompilerError(f"no temporary folder to compile {code.name}.c in: "
                         + "; ".join(failures))


def _load(data: bytes, key: LibraryKey) -> ctypes.CDLL:
    """Load the checked bytes from a memory file (what is loaded is what was checked), or,
    on a system without memory files, from a private copy."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create(f"thetahat_c_{key.name}", getattr(os, "MFD_CLOEXEC", 0))
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            lib = ctypes.CDLL(f"/proc/self/fd/{fd}")
        except BaseException:
            os.close(fd)
            raise
        _memory_files.append(fd)
        return lib
    private = Path(tempfile.mkdtemp(prefix="thetahat-c-")) / key.library_name(
        hashlib.sha256(data).hexdigest())
    with atomic_path(private) as tmp:             # the one way a file is written
        with open(tmp, "wb") as fh:
            _write_all(fh, data)
    return ctypes.CDLL(str(private))


def _cache_folder() -> tuple[Path | None, str | None]:
    try:
        return cache_dir(), None
    except FileAccessError as exc:
        return None, str(exc)


def cached_library(code: CCode) -> ctypes.CDLL:
    """``code``'s shared library (with the record-loop shim), from the cache when a verified
    entry is there, else built, probed, stored and loaded.

    See the module docstring for what is verified. At most one
    :class:`~thetahat.errors.ThetahatWarning` is issued per call: a refused entry (removed
    and rebuilt), or a cache that could not be written (the library then runs from memory).

    Parameters
    ----------
    code : CCode
        Generated C (:func:`~thetahat.codegen.generate.generate_c`).

    Returns
    -------
    ctypes.CDLL
        Loaded once per process per key.

    Raises
    ------
    CCompilerError
        No compiler, it failed, or the library it made failed to load in a child process.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> from thetahat.codegen import generate_c
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> lib = cached_library(code) if find_compiler() else None
    >>> lib is None or hasattr(lib, "prop3_step")
    True
    """
    cc = find_compiler()
    if cc is None:
        raise CCompilerError("no C compiler found: install one (e.g. gcc) or set CC.")
    key = library_key(code, cc)
    with _lock:
        if key.key in _loaded:
            return _loaded[key.key]
        folder, unwritable = _cache_folder()
        notes: list[str] = []
        data = None
        if folder is not None:
            try:
                data = _verified(folder, key)
            except _Refused as why:
                notes.append(f"discarded the cached C library {key.manifest_name} in {folder} "
                             f"({why}) and rebuilt it")
                _discard(folder, key)
        if data is None:
            data = _build(code, folder)
            if folder is None:
                notes.append(f"no cache for the C library ({unwritable}); it runs from memory "
                             "and is built again by the next process")
            else:
                try:
                    _store(folder, key, data)
                except OSError as exc:
                    cause = exc.__cause__ if isinstance(exc.__cause__, OSError) else exc
                    notes.append(f"cannot store the C library in the cache {folder} "
                                 f"({cause.strerror or cause}); it runs from memory and is "
                                 "built again by the next process (free space, or set "
                                 "THETAHAT_CACHE_DIR to a writable folder)")
        lib = _load(data, key)
        _loaded[key.key] = lib
    if notes:
        warnings.warn("; ".join(notes) + ".", ThetahatWarning, stacklevel=3)
    return lib

