"""MATLAB data files: the variables of a ``.mat`` record (MATLAB v4, v5 and v7).

Before SciPy reads a byte of data, :func:`scan_mat` walks the file's element headers itself
(v4 variable headers; v5/v7 data-element tags, the array flags, dimensions and name of each
matrix, the head of each compressed element): it learns each variable's name, class and
dimensions, and checks every declared size against the bytes the file holds and against
:mod:`thetahat.limits` (a compressed element may expand to at most
:data:`~thetahat.limits.MAX_DECOMPRESSED_BYTES`). :func:`load_mat` then lets
:func:`scipy.io.loadmat` read only the variables a record uses, after their compressed
streams have been decompressed once, bounded, to check that they hold what they declare. A
damaged, truncated or hostile file is a :class:`~thetahat.errors.ModelFileError` (or an
:class:`~thetahat.errors.InputLimitError`) that names the file and what is wrong, never
SciPy's own exception.

MATLAB's v7.3 format is an HDF5 container that SciPy cannot read; such a file is refused with
a message saying how to convert it (``save(FILE, '-v7')`` in MATLAB, or an export to CSV).
Which variables become t, u and y is decided by the model file's ``[data]`` table
(:mod:`thetahat.io.mapping`), not here.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from .. import limits
from ..errors import InputLimitError, ModelFileError, ResourceLimitError, ThetahatError
from ..safe_io import open_input

__all__ = ["MAT_SUFFIX", "MatVariable", "load_mat", "read_mat_variables", "scan_mat"]

#: The suffix of MATLAB data files.
MAT_SUFFIX = ".mat"
#: The first bytes of an HDF5 file; a v7.3 MAT file carries them after its 512-byte header.
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_V73_OFFSET = 512
_V5_HEADER = 128
_MI_MATRIX, _MI_COMPRESSED = 14, 15
#: v5 array classes (mxClassID) and their names; the numeric ones with their item size.
_CLASSES = {1: "cell array", 2: "struct", 3: "object", 4: "char", 5: "sparse", 6: "double",
            7: "single", 8: "int8", 9: "uint8", 10: "int16", 11: "uint16", 12: "int32",
            13: "uint32", 14: "int64", 15: "uint64", 16: "function handle",
            17: "opaque object"}
_ITEM = {6: 8, 7: 4, 8: 1, 9: 1, 10: 2, 11: 2, 12: 4, 13: 4, 14: 8, 15: 8}
#: v4 precision digit P → (class, item size).
_V4_PRECISION = {0: (6, 8), 1: (7, 4), 2: (12, 4), 3: (10, 2), 4: (11, 2), 5: (9, 1)}
_READ_CHUNK = 1 << 16
_HEAD_BYTES = 4096


@dataclass(frozen=True, slots=True)
class MatVariable:
    """One variable of a MAT file as its headers declare it (nothing of its data read).

    Attributes
    ----------
    name : str
    cls : int
        MATLAB's class number (6 double, 4 char, 5 sparse, …; see ``describe``).
    dims : tuple of int
    complex, logical : bool
    offset : int
        Byte offset of its element in the file.
    nbytes : int
        Bytes of its element (compressed: on disk).
    compressed : bool
    expanded : int
        Bytes the element declares once decompressed (= ``nbytes`` when not compressed).
    """

    name: str
    cls: int
    dims: tuple[int, ...]
    complex: bool
    logical: bool
    offset: int
    nbytes: int
    compressed: bool
    expanded: int

    @property
    def size(self) -> int:
        """Number of values (the product of the dimensions)."""
        return int(np.prod(self.dims, dtype=object)) if self.dims else 0

    def describe(self) -> str:
        """``rows×cols class``, e.g. ``1×50 double`` or ``50×1 logical``."""
        kind = ("logical" if self.logical else _CLASSES.get(self.cls, f"class {self.cls}"))
        return "×".join(map(str, self.dims)) + f" {'complex ' if self.complex else ''}{kind}"

    def problem(self) -> str | None:
        """Why this variable cannot be a signal, or None."""
        if self.cls not in _CLASSES:
            return (f"of unknown class {self.cls}: the file is damaged or was not written by "
                    f"MATLAB")
        if self.logical:
            return "a logical (true/false) array, not numbers; save it as double(...)"
        if self.cls == 5:
            return "a sparse matrix; save the signal as a full vector: full(x)"
        if self.cls not in _ITEM:
            return (f"not numeric (a {_CLASSES[self.cls]}); save the signal as a numeric "
                    f"vector")
        if self.complex:
            return ("complex values; the estimator needs real signals (map the real part to "
                    "a variable of its own)")
        if sum(d > 1 for d in self.dims) > 1:
            return (f"a {'×'.join(map(str, self.dims))} array, not a vector; save each signal "
                    f"as a row or column vector")
        if self.size > limits.MAX_DATA_SAMPLES:
            return (f"declares {self.size} values, more than the limit of "
                    f"{limits.MAX_DATA_SAMPLES} samples (thetahat.limits.MAX_DATA_SAMPLES)")
        need = self.size * _ITEM[self.cls]
        if need > self.expanded:
            return (f"declares {self.describe()} ({need} bytes) but its element holds "
                    f"{self.nbytes} bytes: the file is damaged")
        return None


class _Damaged(Exception):
    """A header that cannot be what it claims (turned into a ModelFileError)."""


def _read_exact(raw: IO[bytes], offset: int, n: int) -> bytes:
    raw.seek(offset)
    data = raw.read(n)
    if len(data) != n:
        raise _Damaged(f"it ends at byte {offset + len(data)}, inside a header that needs "
                       f"{n} bytes from byte {offset} (the file is truncated)")
    return data


def _tag(buf: bytes, at: int, e: str) -> tuple[int, int, int]:
    """(type, nbytes, header length) of a v5 data-element tag (small element format too)."""
    if len(buf) < at + 8:
        raise _Damaged(f"a data element's tag at byte {at} is cut short")
    first, second = struct.unpack_from(e + "II", buf, at)
    if first >> 16:                                   # small element: 2+2 bytes tag, 4 data
        return first & 0xFFFF, first >> 16, 4
    return first, second, 8


def _matrix_head(buf: bytes, e: str, where: int) -> tuple[int, bool, bool, tuple[int, ...],
                                                          str]:
    """(class, complex, logical, dims, name) from the start of a miMATRIX's content."""
    kind, n, h = _tag(buf, 0, e)
    if kind != 6 or n != 8 or len(buf) < 16:
        raise _Damaged(f"the matrix at byte {where} has no valid array flags")
    flags = struct.unpack_from(e + "I", buf, h)[0]
    cls, bits = flags & 0xFF, (flags >> 8) & 0xFF
    at = h + 8
    kind, n, h = _tag(buf, at, e)
    if kind != 5 or n % 4 or n == 0 or len(buf) < at + h + n:
        raise _Damaged(f"the matrix at byte {where} has no valid dimensions")
    dims = struct.unpack_from(e + f"{n // 4}i", buf, at + h)
    if any(d < 0 for d in dims):
        raise _Damaged(f"the matrix at byte {where} has negative dimensions {dims}")
    at += h + (n if h == 4 else (n + 7) // 8 * 8)
    kind, n, h = _tag(buf, at, e)
    if kind not in (1, 2) or len(buf) < at + h + n:
        raise _Damaged(f"the matrix at byte {where} has no valid name")
    name = buf[at + h:at + h + n].split(b"\0")[0].decode("latin-1")
    return cls, bool(bits & 0x08), bool(bits & 0x02), tuple(dims), name


def _inflate_head(raw: IO[bytes], start: int, nbytes: int, where: int) -> bytes:
    """The first decompressed bytes of a compressed element (at most a few kB)."""
    d = zlib.decompressobj()
    out = b""
    raw.seek(start)
    left = nbytes
    try:
        while len(out) < _HEAD_BYTES and left > 0 and not d.eof:
            chunk = raw.read(min(_READ_CHUNK, left))
            if not chunk:
                break
            left -= len(chunk)
            out += d.decompress(d.unconsumed_tail + chunk, _HEAD_BYTES - len(out))
    except zlib.error as exc:
        raise _Damaged(f"the compressed element at byte {where} is damaged ({exc})") from None
    return out


def _v5_element(raw: IO[bytes], pos: int, size: int, e: str) -> tuple[MatVariable | None, int]:
    """The variable of the element at ``pos`` (None for other elements) and the next
    element's offset."""
    kind, nbytes, h = _tag(_read_exact(raw, pos, 8), 0, e)
    if h == 4:
        return None, pos + 8
    if pos + 8 + nbytes > size:
        raise _Damaged(f"the element at byte {pos} declares {nbytes} bytes, but only "
                       f"{size - pos - 8} follow (the file is truncated or damaged)")
    following = pos + 8 + nbytes + (-nbytes % 8 if kind != _MI_COMPRESSED else 0)
    if kind == _MI_COMPRESSED:
        head = _inflate_head(raw, pos + 8, nbytes, pos)
        if len(head) < 8:
            raise _Damaged(f"the compressed element at byte {pos} holds no element")
        inner, expanded, ih = _tag(head, 0, e)
        if inner != _MI_MATRIX or expanded == 0:
            return None, following
        if expanded > limits.MAX_DECOMPRESSED_BYTES:
            raise InputLimitError(
                f"its compressed element at byte {pos} ({nbytes} bytes) declares {expanded} "
                f"bytes once decompressed, more than the limit of "
                f"{limits.MAX_DECOMPRESSED_BYTES} (thetahat.limits.MAX_DECOMPRESSED_BYTES)")
        cls, cplx, logical, dims, name = _matrix_head(head[ih:], e, pos)
        return MatVariable(name, cls, dims, cplx, logical, pos, nbytes, True,
                           expanded), following
    if kind != _MI_MATRIX or nbytes == 0:
        return None, following
    cls, cplx, logical, dims, name = _matrix_head(
        _read_exact(raw, pos + 8, min(nbytes, _HEAD_BYTES)), e, pos)
    return MatVariable(name, cls, dims, cplx, logical, pos, nbytes, False, nbytes), following


def _scan_v5(raw: IO[bytes], size: int) -> dict[str, MatVariable]:
    head = _read_exact(raw, 0, _V5_HEADER)
    e = {b"IM": "<", b"MI": ">"}.get(head[126:128])
    if e is None:
        raise _Damaged("its 128-byte header has no byte-order mark ('IM' or 'MI' at byte 126)")
    version = struct.unpack_from(e + "H", head, 124)[0]
    if version != 0x0100:
        raise _Damaged(f"its header declares MAT version {version:#06x}, not 0x0100 (v5–v7)")
    out: dict[str, MatVariable] = {}
    pos = _V5_HEADER
    while pos + 8 <= size:
        var, pos = _v5_element(raw, pos, size, e)
        if var is not None:
            out[var.name] = var
    return out


def _v4_header(raw: IO[bytes], pos: int) -> tuple[str, tuple[int, int, int, int, int]]:
    data = _read_exact(raw, pos, 20)
    for e in "<>":
        words = struct.unpack(e + "5i", data)
        if 0 <= words[0] < 5000:
            return e, words
    raise _Damaged(f"the v4 variable header at byte {pos} is not valid")


def _scan_v4(raw: IO[bytes], size: int) -> dict[str, MatVariable]:
    out: dict[str, MatVariable] = {}
    pos = 0
    while pos < size:
        e, (mopt, rows, cols, imagf, namlen) = _v4_header(raw, pos)
        M, O, P, T = mopt // 1000, mopt // 100 % 10, mopt // 10 % 10, mopt % 10
        if M > 4 or O != 0 or P not in _V4_PRECISION or T > 2 or rows < 0 or cols < 0 \
                or imagf not in (0, 1) or not 0 < namlen <= 4096:
            raise _Damaged(f"the v4 variable header at byte {pos} is not valid (type {mopt}, "
                           f"{rows}×{cols}, name of {namlen} bytes)")
        cls, item = _V4_PRECISION[P]
        nbytes = rows * cols * item * (1 + imagf)
        if pos + 20 + namlen + nbytes > size:
            raise _Damaged(f"the v4 variable at byte {pos} declares {rows}×{cols} values "
                           f"({nbytes} bytes), but only {size - pos - 20 - namlen} follow "
                           f"(the file is truncated or damaged)")
        name = _read_exact(raw, pos + 20, namlen).split(b"\0")[0].decode("latin-1")
        cls = {1: 4, 2: 5}.get(T, cls)                 # text, sparse
        out[name] = MatVariable(name, cls, (rows, cols), bool(imagf), False, pos, nbytes,
                                False, nbytes)
        pos += 20 + namlen + nbytes
    return out


def _is_v73(head: bytes) -> bool:
    return (head[_V73_OFFSET:_V73_OFFSET + 8] == _HDF5_SIGNATURE
            or head.startswith(_HDF5_SIGNATURE) or b"MATLAB 7.3 MAT-file" in head[:116])


def scan_mat(path: Path, raw: IO[bytes]) -> dict[str, MatVariable]:
    """The variables of an open MAT file, from its headers, every declared size checked.

    Parameters
    ----------
    path : Path
        For messages.
    raw : binary file
        The open file (seekable).

    Returns
    -------
    dict of str to MatVariable

    Raises
    ------
    ModelFileError
        The file is empty, too short, truncated, damaged, not a MAT file, or a v7.3 (HDF5)
        file (the message says how to re-save it).
    InputLimitError
        A compressed element declares more than
        :data:`thetahat.limits.MAX_DECOMPRESSED_BYTES`.

    Examples
    --------
    >>> import io, pathlib, tempfile
    >>> import numpy as np, scipy.io
    >>> from thetahat.io.matfile import scan_mat
    >>> buf = io.BytesIO()
    >>> scipy.io.savemat(buf, {"qm": np.zeros((5, 1)), "ok": np.array([[True]])})
    >>> {n: v.describe() for n, v in scan_mat(pathlib.Path("x.mat"), buf).items()}
    {'qm': '5×1 double', 'ok': '1×1 logical'}
    """
    raw.seek(0, 2)
    size = raw.tell()
    raw.seek(0)
    head = raw.read(_V73_OFFSET + 8)
    try:
        if size == 0:
            raise _Damaged("it is empty (0 bytes)")
        if _is_v73(head):
            raise ModelFileError(
                f"data file {path} is a MATLAB v7.3 (HDF5) file, which thetahat does not "
                f"read; re-save it in MATLAB with save('{path.name}', '-v7') (or list the "
                f"variables: save('{path.name}', 't', 'u', 'y', '-v7')), or export the "
                f"variables to CSV.")
        if 0 in head[:4]:
            return _scan_v4(raw, size)
        if size < _V5_HEADER:
            raise _Damaged(f"it has {size} bytes, fewer than the 128-byte header of a v5/v7 "
                           f"MAT file")
        return _scan_v5(raw, size)
    except _Damaged as exc:
        raise ModelFileError(f"cannot read data file {path} as a MATLAB file: {exc}; re-save "
                             f"it from MATLAB (save('{path.name}', '-v7')) or export it to "
                             f"CSV.") from None
    except InputLimitError as exc:
        raise InputLimitError(f"data file {path}: {exc}; split the record or raise the "
                              f"limit.") from None


def _check_stream(path: Path, raw: IO[bytes], var: MatVariable) -> None:
    """Decompress a compressed element once, bounded, and check it holds what it declares."""
    d = zlib.decompressobj()
    raw.seek(var.offset + 8)
    left, out = var.nbytes, 0
    bound = var.expanded + 8
    try:
        while left > 0 and not d.eof:
            chunk = raw.read(min(_READ_CHUNK, left))
            if not chunk:
                break
            left -= len(chunk)
            data = d.unconsumed_tail + chunk
            while data and not d.eof:
                out += len(d.decompress(data, _READ_CHUNK))
                data = d.unconsumed_tail
                if out > bound:
                    raise ModelFileError(
                        f"data file {path}, variable {var.name!r}: its compressed element "
                        f"expands beyond the {var.expanded} bytes it declares: the file is "
                        f"damaged or hostile.")
    except zlib.error as exc:
        raise ModelFileError(f"data file {path}, variable {var.name!r}: its compressed data "
                             f"are damaged ({exc}); re-save the file or export it to "
                             f"CSV.") from None
    if not d.eof or out != bound:
        raise ModelFileError(f"data file {path}, variable {var.name!r}: its compressed data "
                             f"end early ({out} of {bound} bytes): the file is truncated or "
                             f"damaged.")


def load_mat(path: Path, raw: IO[bytes], names: Sequence[str],
             variables: dict[str, MatVariable]) -> dict[str, Any]:
    """Read the named variables of a scanned MAT file with :func:`scipy.io.loadmat`.

    Parameters
    ----------
    path : Path
    raw : binary file
        The open file.
    names : sequence of str
        Variables to read (each a key of ``variables``).
    variables : dict of str to MatVariable
        From :func:`scan_mat`.

    Returns
    -------
    dict of str to object
        Name to value, as SciPy reads it (numeric variables as 2-D arrays).

    Raises
    ------
    ModelFileError
        A compressed element is damaged, expands beyond what it declares, or SciPy cannot
        read the variable.
    ResourceLimitError
        The variables do not fit in memory.
    """
    from scipy.io import loadmat

    need = sum(variables[n].expanded for n in names)
    limits.check_allocation(2.0 * need, f"reading the variables {list(names)} of {path}",
                            fix="save only the signals the record needs")
    for name in names:
        if variables[name].compressed:
            _check_stream(path, raw, variables[name])
    raw.seek(0)
    try:
        contents = loadmat(raw, squeeze_me=False, mat_dtype=False,
                           variable_names=list(names))
    except ThetahatError:
        raise
    except MemoryError as exc:
        raise ResourceLimitError(f"reading data file {path} ran out of memory; save only the "
                                 f"signals the record needs.") from exc
    except Exception as exc:  # noqa: BLE001 - SciPy's reader on bytes it cannot read
        raise ModelFileError(f"cannot read data file {path} as a MATLAB file: "
                             f"{type(exc).__name__}: {exc}; re-save it from MATLAB or export "
                             f"it to CSV.") from exc
    missing = [n for n in names if n not in contents]
    if missing:
        raise ModelFileError(f"data file {path}: SciPy found no variable {missing[0]!r} where "
                             f"its header is; the file is damaged.")
    return {n: contents[n] for n in names}


def read_mat_variables(path: str | Path, names: Sequence[str] | None = None) -> dict[str, Any]:
    """The variables of a MATLAB v4/v5/v7 file, by name, as SciPy reads them.

    The file is scanned (:func:`scan_mat`) before SciPy reads it. The values are returned
    unchecked (numeric arrays, but also strings, cells, structs or sparse matrices, whatever
    the file holds); :func:`thetahat.io.datafile.read_data` checks the ones a model uses.

    Parameters
    ----------
    path : str or Path
        A ``.mat`` file saved by MATLAB (``-v4``, ``-v6``, ``-v7``; the default of ``save``
        without ``-v7.3``) or by :func:`scipy.io.savemat`, within
        :data:`thetahat.limits.MAX_DATA_FILE_BYTES`.
    names : sequence of str, optional
        The variables to read (default: all).

    Returns
    -------
    dict of str to object
        Variable name to value (numeric variables as 2-D ndarrays, as MATLAB stores them).

    Raises
    ------
    ModelFileError
        The file cannot be read, is not a MATLAB file, is damaged, lacks a named variable, or
        is a v7.3 (HDF5) file: re-save it in MATLAB with ``save('FILE.mat', 'VAR1', 'VAR2',
        '-v7')`` or export the variables to CSV.
    InputLimitError
        The file or one of its compressed elements exceeds :mod:`thetahat.limits`.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np, scipy.io
    >>> from thetahat.io.matfile import read_mat_variables
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "log.mat"
    >>> scipy.io.savemat(path, {"t": np.arange(3.0), "qm": np.zeros((3, 1))})
    >>> {k: v.shape for k, v in read_mat_variables(path).items()}
    {'t': (1, 3), 'qm': (3, 1)}
    """
    path = Path(path)
    with open_input(path, "data file", limits.MAX_DATA_FILE_BYTES) as raw:
        variables = scan_mat(path, raw)
        wanted = list(variables) if names is None else list(names)
        missing = [n for n in wanted if n not in variables]
        if missing:
            raise ModelFileError(f"data file {path} has no variable(s) {missing}; it has "
                                 f"{sorted(variables)}.")
        return load_mat(path, raw, wanted, variables)
