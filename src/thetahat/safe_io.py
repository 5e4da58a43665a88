"""Files in and out: every output is written atomically and never over an input; only regular
files are read, within a size limit.

Outputs
    :func:`atomic_path` (for libraries that write by path: NumPy, pyarrow, Matplotlib) and
    :func:`write_text` write into a temporary file in the output's own folder, flush and
    ``fsync`` it, and ``os.replace`` it over the output: a failure (a full disk, ``ulimit
    -f``, an exception) leaves the old output untouched and no partial file behind.
    :func:`write_texts` writes a set of files that belong together (the generated C): every
    one is written and flushed first, then all are renamed, so a full disk replaces none.
    :func:`check_writable` is called on every output path before any work: it refuses a
    directory, an unwritable place, a suffix the writer does not know, and a path that resolves
    to one of the inputs (the same file, a symlink or hard link to it). :func:`atomic_path`
    itself refuses to replace a file this process has read as an input (through
    :func:`open_input` or :func:`check_regular`) and that has not changed since: a library
    caller that passes an input as an output is stopped at the write, not only the CLI.
Inputs
    :func:`open_input` opens a file without blocking, checks that it is a regular file (not a
    FIFO, a device such as ``/dev/zero``, or a symlink to one) and that its size is within the
    limit (:data:`thetahat.limits.MAX_MODEL_FILE_BYTES`,
    :data:`thetahat.limits.MAX_DATA_FILE_BYTES`) before a byte is read.
"""

from __future__ import annotations

import contextlib
import io
import os
import secrets
import signal
import stat
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from .errors import FileAccessError, InputLimitError, ModelFileError

__all__ = ["atomic_path", "write_text", "write_texts", "check_writable", "check_regular",
           "open_input", "read_text", "same_file"]


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character "
                        "device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISDIR, "a directory")):
        if test(mode):
            return name
    return "not a regular file"


#: The files this process has accepted as inputs, as (device, inode, mtime in ns, size):
#: :func:`atomic_path` does not replace one of them (a file changed since it was read, or a
#: new file on a reused inode, has another mtime and is not an input any more).
_INPUTS: set[tuple[int, int, int, int]] = set()


def _identity(st: os.stat_result) -> tuple[int, int, int, int]:
    return st.st_dev, st.st_ino, st.st_mtime_ns, st.st_size


def _check_stat(st: os.stat_result, path: Path, what: str, limit: int | None) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise ModelFileError(f"cannot read {what} {path}: it is {_kind(st.st_mode)}; thetahat "
                             f"reads only regular files (copy the content into a file).")
    if limit is not None and st.st_size > limit:
        raise InputLimitError(f"cannot read {what} {path}: it has {st.st_size} bytes, more "
                              f"than the limit of {limit} bytes (thetahat.limits); raise the "
                              f"limit or split the file.")
    _INPUTS.add(_identity(st))


def check_regular(path: str | Path, what: str, limit: int | None = None) -> Path:
    """Check, without opening it, that ``path`` is a regular file within ``limit`` bytes.

    Symlinks are followed: a link to a regular file is fine, a link to ``/dev/zero`` is not.

    Parameters
    ----------
    path : str or Path
    what : str
        Names the file in messages ("data file", "model file").
    limit : int, optional
        Largest accepted size in bytes (no limit when None).

    Returns
    -------
    Path

    Raises
    ------
    ModelFileError
        The file does not exist, cannot be inspected, or is not a regular file.
    InputLimitError
        The file is larger than ``limit``.

    Examples
    --------
    >>> from thetahat.safe_io import check_regular
    >>> check_regular("/dev/zero", "data file")
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: cannot read data file /dev/zero: it is a character device; ...
    """
    path = Path(path)
    try:
        st = os.stat(path)
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"cannot read {what} {path}: {exc}") from exc
    _check_stat(st, path, what, limit)
    return path


def open_input(path: str | Path, what: str, limit: int | None = None) -> IO[bytes]:
    """Open a regular file for reading in binary mode, refusing anything else before reading.

    The file is opened with ``O_NONBLOCK`` (so a FIFO cannot block the open), checked with
    ``fstat`` on the open descriptor (so a file swapped between check and open is caught), and
    then switched back to blocking reads.

    Parameters
    ----------
    path : str or Path
    what : str
        Names the file in messages.
    limit : int, optional
        Largest accepted size in bytes.

    Returns
    -------
    binary file object
        The caller closes it (use it in a ``with`` block).

    Raises
    ------
    ModelFileError
        The file cannot be opened or is not a regular file.
    InputLimitError
        The file is larger than ``limit``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.safe_io import open_input
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.txt"
    >>> _ = p.write_text("hello")
    >>> with open_input(p, "text file", limit=100) as fh:
    ...     fh.read()
    b'hello'
    """
    path = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"cannot read {what} {path}: {exc}") from exc
    try:
        _check_stat(os.fstat(fd), path, what, limit)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_text(path: str | Path, what: str, limit: int | None = None) -> str:
    """The text of a regular UTF-8 file (a byte-order mark is dropped), read via
    :func:`open_input`.

    Parameters
    ----------
    path : str or Path
    what : str
        Names the file in messages.
    limit : int, optional
        Largest accepted size in bytes.

    Returns
    -------
    str

    Raises
    ------
    ModelFileError
        Not a regular file, unreadable, or not UTF-8.
    InputLimitError
        Larger than ``limit``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.safe_io import read_text
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "m.toml"
    >>> _ = p.write_bytes("\\ufeffa = 1".encode())
    >>> read_text(p, "model file")
    'a = 1'
    """
    with open_input(path, what, limit) as fh:
        try:
            return io.TextIOWrapper(fh, encoding="utf-8-sig", newline=None).read()
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelFileError(f"cannot read {what} {path}: {exc}") from exc


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when ``a`` and ``b`` name the same file (same path after resolving symlinks, or the
    same inode: a hard link).

    Parameters
    ----------
    a, b : str or Path

    Returns
    -------
    bool

    Examples
    --------
    >>> from thetahat.safe_io import same_file
    >>> same_file("/tmp/../tmp/x.csv", "/tmp/x.csv")
    True
    """
    pa, pb = Path(a), Path(b)
    try:
        if pa.resolve() == pb.resolve():
            return True
        return pa.exists() and pb.exists() and os.path.samefile(pa, pb)
    except (OSError, ValueError, RuntimeError):
        return False


def check_writable(path: str | Path, *, inputs: Iterable[str | Path] = (),
                   suffixes: Iterable[str] | None = None, what: str = "output") -> Path:
    """Check, before any work, that an output file can be written (without creating it).

    Parameters
    ----------
    path : str or Path
        The output file.
    inputs : iterable of str or Path, optional
        Files the run reads: the output may not be any of them (nor a link to one).
    suffixes : iterable of str, optional
        The suffixes the writer knows (lower case, with the dot); None accepts any.
    what : str
        Names the output in messages.

    Returns
    -------
    Path

    Raises
    ------
    ModelFileError
        ``path`` is a directory, resolves to an input, has an unknown suffix, is an existing
        file that is not writable, or lies in a folder that cannot be created or written.

    Examples
    --------
    >>> import tempfile
    >>> from thetahat.safe_io import check_writable
    >>> check_writable(tempfile.mkdtemp())
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: cannot write ...: it is a directory; give a file name...
    >>> check_writable("/tmp/data.csv", inputs=["/tmp/data.csv"])
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: cannot write /tmp/data.csv: it is an input of this run ...
    """
    path = Path(path)
    name_max = _name_max(path.parent)
    if len(os.fsencode(path.name)) > name_max:
        raise ModelFileError(f"cannot write {what} {str(path)[:80]}…: its name has "
                             f"{len(os.fsencode(path.name))} bytes, more than the "
                             f"{name_max} the file system allows; choose a shorter name.")
    for source in inputs:
        if same_file(path, source):
            raise ModelFileError(f"cannot write {path}: it is an input of this run ({source}); "
                                 f"writing it would destroy the input. Choose another output "
                                 f"path (-o).")
    if path.is_dir():
        raise ModelFileError(f"cannot write {path}: it is a directory; give a file name, e.g. "
                             f"{path / 'estimates.csv'}.")
    if suffixes is not None:
        allowed = tuple(suffixes)
        if path.suffix.lower() not in allowed:
            raise ModelFileError(f"cannot write {what} {path}: the suffix must be one of "
                                 f"{', '.join(allowed)}; got {path.suffix or '(none)'!r}.")
    if path.exists() or path.is_symlink():
        if not path.exists() or not stat.S_ISREG(os.stat(path).st_mode):
            raise ModelFileError(f"cannot write {path}: it exists and is not a regular file.")
        if not os.access(path, os.W_OK):
            raise ModelFileError(f"cannot write {path}: the file is not writable.")
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise ModelFileError(f"cannot write {path}: {folder} is not a writable folder; choose "
                             f"another output path (-o).")
    return path


def _name_max(folder: Path) -> int:
    """The longest file name (bytes) the file system of ``folder`` (or of its nearest existing
    parent) allows; 255 when unknown."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return                              # not supported (Windows): the rename still holds
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: The temporary folders of the writes in progress (removed by :func:`_on_signal`).
_TEMPORARIES: set[Path] = set()
#: The handlers :func:`_on_signal` replaced, by signal number (restored when no write is left).
_PREVIOUS: dict[int, Any] = {}
#: Signals whose default action ends the process without running ``finally`` blocks.
_CLEANUP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


def _remove(folder: Path) -> None:
    with contextlib.suppress(OSError):
        for entry in folder.iterdir():
            entry.unlink()
        folder.rmdir()


def _on_signal(signum: int, frame: Any) -> None:
    """SIGTERM or SIGHUP during a write: remove the temporary files, then do what the signal
    would have done (the previous handler, or the default action: the process ends)."""
    for folder in list(_TEMPORARIES):
        _remove(folder)
    _TEMPORARIES.clear()
    previous = _PREVIOUS.pop(signum, signal.SIG_DFL)
    signal.signal(signum, previous)
    if callable(previous):
        previous(signum, frame)
    elif previous == signal.SIG_DFL:
        os.kill(os.getpid(), signum)


def _register(folder: Path) -> None:
    _TEMPORARIES.add(folder)
    if threading.current_thread() is not threading.main_thread():
        return                      # handlers can be set from the main thread only
    for sig in _CLEANUP_SIGNALS:
        if sig in _PREVIOUS:
            continue
        current = signal.getsignal(sig)
        if current == signal.SIG_IGN or current is None:
            continue                # ignored (nohup) or set from C: leave it alone
        _PREVIOUS[sig] = current
        signal.signal(sig, _on_signal)


def _unregister(folder: Path) -> None:
    _TEMPORARIES.discard(folder)
    if _TEMPORARIES or threading.current_thread() is not threading.main_thread():
        return
    for sig, previous in list(_PREVIOUS.items()):
        if signal.getsignal(sig) is _on_signal:
            signal.signal(sig, previous)
        del _PREVIOUS[sig]


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write ``path``'s content to; on success it replaces ``path``.

    The temporary file has the output's own name (writers that choose the format by suffix
    still work, and its name fits wherever the output's does), inside a new hidden folder
    ``.thetahat-<hex>.tmp`` next to the output: no reader of records takes it (folders and
    globs of a fleet skip hidden names and do not enter folders). On leaving the block without
    an error the file is flushed to disk and renamed over ``path`` (``os.replace``, atomic on
    POSIX); on an error, and on SIGTERM or SIGHUP during the block (a handler removes the
    temporary folder, then lets the signal do what it would have done), the temporary folder
    is removed and ``path`` is left as it was. The output's folder is created when missing.

    Parameters
    ----------
    path : str or Path
        The final output file.

    Yields
    ------
    Path
        Where to write.

    Raises
    ------
    FileAccessError
        ``path`` is a file this process read as an input (unchanged since), or the folder
        cannot be created, or the file cannot be written or renamed.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.safe_io import atomic_path
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "table.csv"
    >>> with atomic_path(out) as tmp:
    ...     _ = tmp.write_text("t,y\\n0,1\\n")
    ...     tmp.name == out.name and tmp.parent.name.startswith(".thetahat-")
    True
    >>> out.read_text(), sorted(p.name for p in out.parent.iterdir())
    ('t,y\\n0,1\\n', ['table.csv'])
    """
    path = Path(path)
    try:
        existing = _identity(os.stat(path))
    except OSError:
        existing = None
    if existing in _INPUTS:                     # FileAccessError is an OSError: raised here
        raise FileAccessError(f"will not write {path}: this process read it as an input, "
                              f"and an output never replaces an input; write the output to "
                              f"another path.")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        folder = _new_temporary(path)
    except OSError as exc:
        raise FileAccessError(f"cannot write {path}: {exc}; choose a writable output "
                              f"path.") from exc
    tmp = folder / path.name
    _register(folder)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        os.close(fd)
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if path.exists():                       # keep the mode of the file replaced
            os.chmod(tmp, os.stat(path).st_mode & 0o7777)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        raise FileAccessError(f"cannot write {path}: {exc}; the previous content (if any) is "
                              f"unchanged.") from exc
    finally:
        _remove(folder)
        _unregister(folder)


def _new_temporary(path: Path) -> Path:
    """A new hidden folder next to ``path`` for its temporary file."""
    for _ in range(100):
        folder = path.parent / f".thetahat-{secrets.token_hex(6)}.tmp"
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:
            continue
        return folder
    raise FileAccessError(f"cannot write {path}: no free temporary name in its folder.")


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`).

    Parameters
    ----------
    path : str or Path
    text : str

    Returns
    -------
    Path

    Raises
    ------
    FileAccessError
        The file cannot be written; an old file at ``path`` is unchanged.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.safe_io import write_text
    >>> write_text(pathlib.Path(tempfile.mkdtemp()) / "a.json", "{}").read_text()
    '{}'
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
    return path


def write_texts(files: dict[Path, str]) -> tuple[Path, ...]:
    """Write several text files (UTF-8) as one set: all written first, then all renamed.

    Every file is written and ``fsync``-ed into a temporary folder next to it (as
    :func:`atomic_path`) before any is renamed over its output, so a failure while writing (a
    full disk, ``ulimit -f``) replaces none of them. The renames follow; should one fail (a
    folder made read-only meanwhile), the error says which files were replaced and which kept
    their previous content.

    Parameters
    ----------
    files : dict
        Output path → text.

    Returns
    -------
    tuple of Path
        The outputs, in the order given.

    Raises
    ------
    FileAccessError
        An output is a file this process read as an input, or a file cannot be written or
        renamed; the message says what was replaced (nothing, when the writing failed).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.safe_io import write_texts
    >>> out = pathlib.Path(tempfile.mkdtemp())
    >>> [p.name for p in write_texts({out / "a.h": "int a;\\n", out / "a.c": "int b;\\n"})]
    ['a.h', 'a.c']
    """
    paths = [Path(p) for p in files]
    for path in paths:
        try:
            existing: tuple[int, int, int, int] | None = _identity(os.stat(path))
        except OSError:
            existing = None
        if existing in _INPUTS:
            raise FileAccessError(f"will not write {path}: this process read it as an input, "
                                  f"and an output never replaces an input; write the output "
                                  f"to another folder.")
    folders: dict[Path, Path] = {}
    replaced: list[Path] = []
    try:
        try:
            temporaries = []
            for path, text in zip(paths, files.values()):
                if path.parent not in folders:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    folders[path.parent] = _new_temporary(path)
                    _register(folders[path.parent])
                tmp = folders[path.parent] / path.name
                with open(tmp, "x", encoding="utf-8", newline="") as fh:
                    fh.write(text)
                    fh.flush()
                    os.fsync(fh.fileno())
                if path.exists():               # keep the mode of the file replaced
                    os.chmod(tmp, os.stat(path).st_mode & 0o7777)
                temporaries.append(tmp)
        except OSError as exc:
            raise FileAccessError(f"cannot write {path}: {exc}; none of the "
                                  f"{len(paths)} files was replaced (their previous content, "
                                  f"if any, is unchanged).") from exc
        for path, tmp in zip(paths, temporaries):
            try:
                os.replace(tmp, path)
            except OSError as exc:
                kept = [str(p) for p in paths[len(replaced):]]
                done = ", ".join(str(p) for p in replaced) or "none"
                raise FileAccessError(f"cannot rename the new {path} into place: {exc}; "
                                      f"replaced: {done}; previous content kept: "
                                      f"{', '.join(kept)}. Write them again.") from exc
            replaced.append(path)
        for folder in folders:
            _fsync_dir(folder)
    finally:
        for folder in folders.values():
            _remove(folder)
            _unregister(folder)
    return tuple(paths)
