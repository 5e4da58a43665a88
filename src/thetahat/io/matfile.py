"""MATLAB data files: the variables of a ``.mat`` record (MATLAB v4, v5 and v7, via SciPy).

MATLAB's v7.3 format is an HDF5 container that :func:`scipy.io.loadmat` cannot read; such a
file is refused with a message saying how to convert it (``save(FILE, '-v7')`` in MATLAB, or
an export to CSV). Which variables become t, u and y is decided by the model file's ``[data]``
table (:mod:`thetahat.io.mapping`), not here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ModelFileError

__all__ = ["MAT_SUFFIX", "describe_variables", "read_mat_variables"]

#: The suffix of MATLAB data files.
MAT_SUFFIX = ".mat"
#: The first bytes of an HDF5 file; a v7.3 MAT file carries them after its 512-byte header.
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_V73_OFFSET = 512


def _is_v73(path: Path) -> bool:
    with path.open("rb") as fh:
        head = fh.read(_V73_OFFSET + len(_HDF5_SIGNATURE))
    return (head[_V73_OFFSET:] == _HDF5_SIGNATURE or head.startswith(_HDF5_SIGNATURE)
            or b"MATLAB 7.3 MAT-file" in head[:116])


def read_mat_variables(path: str | Path) -> dict[str, Any]:
    """The variables of a MATLAB v4/v5/v7 file, by name, as SciPy reads them.

    The values are returned unchecked (numeric arrays, but also strings, cells, structs or
    sparse matrices, whatever the file holds); :mod:`thetahat.io.mapping` checks the ones a
    model uses. SciPy's bookkeeping entries (``__header__``, ``__version__``,
    ``__globals__``) are left out.

    Parameters
    ----------
    path : str or Path
        A ``.mat`` file saved by MATLAB (``-v4``, ``-v6``, ``-v7``; the default before
        MATLAB R2006b and of ``save`` without ``-v7.3``) or by :func:`scipy.io.savemat`.

    Returns
    -------
    dict of str to object
        Variable name to value (numeric variables as 2-D ndarrays, as MATLAB stores them).

    Raises
    ------
    ModelFileError
        The file cannot be read, is not a MATLAB file, or is a v7.3 (HDF5) file: re-save it
        in MATLAB with ``save('FILE.mat', 'VAR1', 'VAR2', '-v7')`` or export the variables
        to CSV.

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
    from scipy.io import loadmat

    path = Path(path)
    try:
        if _is_v73(path):
            raise ModelFileError(
                f"data file {path} is a MATLAB v7.3 (HDF5) file, which thetahat does not "
                f"read; re-save it in MATLAB with save('{path.name}', '-v7') (or list the "
                f"variables: save('{path.name}', 't', 'u', 'y', '-v7')), or export the "
                f"variables to CSV.")
        contents = loadmat(path, squeeze_me=False, mat_dtype=False)
    except NotImplementedError as exc:           # SciPy's own v7.3 refusal
        raise ModelFileError(f"data file {path}: {exc}; re-save it in MATLAB with "
                             f"save('{path.name}', '-v7') or export it to CSV.") from exc
    except (OSError, ValueError, TypeError) as exc:
        raise ModelFileError(f"cannot read data file {path} as a MATLAB file: {exc}") from exc
    return {k: v for k, v in contents.items() if not k.startswith("__")}


def describe_variables(variables: dict[str, Any]) -> str:
    """The variables as ``name (rows×cols type)``, comma-separated, for messages.

    Parameters
    ----------
    variables : dict of str to object
        As returned by :func:`read_mat_variables`.

    Returns
    -------
    str

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.io.matfile import describe_variables
    >>> describe_variables({"qm": np.zeros((5, 1)), "name": np.array(["EMPS"])})
    "'qm' (5×1 float64), 'name' (1 <U4)"
    """
    parts = []
    for name, value in variables.items():
        shape = getattr(value, "shape", None)
        dtype = getattr(value, "dtype", None)
        what = ("×".join(str(s) for s in shape) if shape is not None else "?") + \
            f" {dtype if dtype is not None else type(value).__name__}"
        parts.append(f"{name!r} ({what})")
    return ", ".join(parts) if parts else "(none)"
