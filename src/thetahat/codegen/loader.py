"""Compile generated C with the system compiler and call it through ctypes (tests, benchmarks).

:func:`find_compiler` locates ``$CC`` or ``cc``; :func:`build` compiles a :class:`CCode` — as
a shared library with a small record-loop shim (:func:`load_c`), or as the harness executable
(:func:`build_harness`, which also takes sanitizer flags). The shim is not part of the generated
code: it only loops ``<name>_step`` over a record inside C so that a whole run costs one call.

What lives here: the compiler calls, :class:`CObserver` (the generated observer through
ctypes) and its record run :class:`CRun`, whose ``status`` is a
:class:`~thetahat.estimation.status.Status`. What it may import: the generator and harness of
this package, :mod:`thetahat.estimation.status`, :mod:`thetahat.safe_io` and the errors.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import CCompilerError, DimensionError
from ..estimation.status import Status, status_error
from ..safe_io import write_text
from .c_api import STATUS as C_STATUS
from .generate import CCode
from .harness import C_FLAGS

__all__ = ["CObserver", "CRun", "build", "build_harness", "build_many", "find_compiler", "load_c",
           "shim_source", "STATUS"]

#: Status codes of the generated functions (``<NAME>_OK``…), by name (:data:`.c_api.STATUS`).
STATUS = {name: code for name, (code, _) in C_STATUS.items()}

_SHIM = r"""/* ctypes shim (thetahat.codegen.loader): loops @P@_step over a record. */
#include "@P@.h"

typedef @P@_real_t real_t;

enum { NS = @NS@, NUB = @PU@_NU > 0 ? @PU@_NU : 1 };

static void store(const @P@_state *s, real_t row[])
{
    int i;
    for (i = 0; i < NS; ++i) {
        row[i] = s->s[i];
    }
}

/* Rows i of S and PHI: the state before sample i and phi_hat at sample i (as run() records). */
int @P@_run_record(@P@_state *s, long N, const real_t U[], const real_t Y[], real_t S[],
                   real_t PHI[], long *index)
{
    long i;
    int status;
    for (i = 0; i < N; ++i) {
        *index = i;
        store(s, S + i * NS);
        status = @P@_phi_hat(s, U + i * NUB, Y + i * @PU@_NY,
                             PHI + i * @PU@_NK);
        if (status != 0) {
            return status;
        }
        if (i + 1 < N) {
            status = @P@_step(s, U + i * NUB, Y + i * @PU@_NY@NEXT@);
            if (status != 0) {
                return status;
            }
        }
    }
    return 0;
}

/* N steps and nothing else (for timing). */
int @P@_run_steps(@P@_state *s, long N, const real_t U[], const real_t Y[])
{
    long i;
    int status;
    for (i = 0; i + @FOH@ < N; ++i) {
        status = @P@_step(s, U + i * NUB, Y + i * @PU@_NY@NEXT@);
        if (status != 0) {
            return status;
        }
    }
    return 0;
}
"""


def find_compiler() -> str | None:
    """Path of ``$CC`` (default ``cc``), or None when there is none.

    Returns
    -------
    str or None

    Examples
    --------
    >>> isinstance(find_compiler(), (str, type(None)))
    True
    """
    return shutil.which(os.environ.get("CC", "cc"))


def _compile(cmd: Sequence[str], cwd: Path) -> None:
    try:
        out = subprocess.run(list(cmd), cwd=cwd, capture_output=True, text=True, timeout=300)
    except OSError as exc:
        raise CCompilerError(f"cannot run the C compiler ({cmd[0]}): {exc}") from exc
    if out.returncode != 0 or out.stderr.strip():
        raise CCompilerError(f"{' '.join(cmd)} failed (exit {out.returncode}):\n"
                             f"{out.stderr.strip()}")


def _compiler() -> str:
    cc = find_compiler()
    if cc is None:
        raise CCompilerError("no C compiler found: install one (e.g. gcc) or set CC.")
    return cc


def shim_source(code: CCode) -> str:
    """The record-loop shim ``<name>_shim.c`` compiled with ``code`` into a shared library.

    Parameters
    ----------
    code : CCode

    Returns
    -------
    str

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> from thetahat.codegen import generate_c
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> "int prop3_run_record(" in shim_source(code)
    True
    """
    P = code.name
    foh = code.hold == "foh"
    nxt = ", U + (i + 1) * NUB, Y + (i + 1) * @PU@_NY" if foh else ""
    return (_SHIM.replace("@NEXT@", nxt).replace("@FOH@", "1" if foh else "0")
            .replace("@NS@", str(code.sizes["state"])).replace("@PU@", P.upper())
            .replace("@P@", P))


def _write_with_shim(code: CCode, out: Path) -> list[str]:
    """Write ``code`` and its record-loop shim into ``out``; the two C files' names."""
    code.write(out)
    P = code.name
    write_text(out / f"{P}_shim.c", shim_source(code))
    return [f"{P}.c", f"{P}_shim.c"]


def build_many(codes: Sequence[CCode], directory: str | Path, *,
               flags: Sequence[str] = C_FLAGS) -> Path:
    """Compile several generated observers (distinct names) into one shared library.

    One compiler run for all of them (the conformance tests build dozens of configurations).

    Parameters
    ----------
    codes : sequence of CCode
    directory : str or Path
    flags : sequence of str

    Returns
    -------
    Path
        ``libobservers.so``; load each with ``CObserver(code, path)``.

    Raises
    ------
    CCompilerError
        No compiler, or it failed or warned.
    """
    out = Path(directory)
    names = [code.name for code in codes]
    if len(set(names)) != len(names):
        raise CCompilerError(f"build_many needs distinct names; got {names}.")
    sources = [f for code in codes for f in _write_with_shim(code, out)]
    lib = out / "libobservers.so"
    _compile([_compiler(), *flags, "-fPIC", "-shared", "-o", lib.name, *sources, "-lm"], out)
    return lib


def build(code: CCode, directory: str | Path, *, flags: Sequence[str] = C_FLAGS) -> Path:
    """Write ``code`` into ``directory`` and compile it with the shim as a shared library.

    Parameters
    ----------
    code : CCode
    directory : str or Path
    flags : sequence of str
        Compiler flags (default: the acceptance's, with ``-Werror``).

    Returns
    -------
    Path
        The library ``lib<name>.so``.

    Raises
    ------
    CCompilerError
        No compiler, or it failed or warned (the flags include ``-Werror``).
    """
    out = Path(directory)
    P = code.name
    sources = _write_with_shim(code, out)
    lib = out / f"lib{P}.so"
    _compile([_compiler(), *flags, "-fPIC", "-shared", "-o", lib.name, *sources, "-lm"], out)
    return lib


def build_harness(code: CCode, directory: str | Path, *,
                  flags: Sequence[str] = C_FLAGS) -> Path:
    """Write ``code`` and compile the CSV harness ``<name>`` (as its Makefile does).

    Parameters
    ----------
    code : CCode
    directory : str or Path
    flags : sequence of str
        Compiler flags; e.g. ``(*C_FLAGS, "-fsanitize=address,undefined")``.

    Returns
    -------
    Path
        The executable.
    """
    out = Path(directory)
    code.write(out)
    P = code.name
    _compile([_compiler(), *flags, "-o", P, f"{P}_main.c", f"{P}.c", "-lm"], out)
    return out / P


@dataclass(frozen=True, slots=True, eq=False)
class CRun:
    """A record run in C: the estimates of an :class:`~thetahat.estimation.protocol.EstimateResult`
    in the generated precision, and the status that ended the run.

    Attributes
    ----------
    x_hat, phi_hat, theta_hat : ndarray
        Shapes (N, n), (N, k), (N, p), in the generated precision.
    x_hat_refined : ndarray or None
    status : Status
        ``OK``, or the status of the code that stopped the run at row ``index`` (rows after
        it are zeros: not computed).
    index : int
    """

    x_hat: NDArray[Any]
    phi_hat: NDArray[Any]
    theta_hat: NDArray[Any]
    x_hat_refined: NDArray[Any] | None
    status: Status
    index: int


class CObserver:
    """A generated observer loaded with ctypes (build it with :func:`load_c`).

    ``init``, ``step`` and ``run`` call ``<name>_init``, ``<name>_step`` and the shim's record
    loop; the state is a numpy vector col(x̂, z, θ̂[, x̂₂]) in the generated precision.

    Parameters
    ----------
    code : CCode
        The generated sources.
    library : Path or ctypes.CDLL
        The shared library built from them by :func:`build`, or that library already loaded
        (:func:`~thetahat.codegen.native_cache.cached_library`).
    """

    def __init__(self, code: CCode, library: Path | ctypes.CDLL) -> None:
        self.code = code
        self.dtype = np.float64 if code.real == "double" else np.float32
        ctype = ctypes.c_double if code.real == "double" else ctypes.c_float
        self._ptr = ctypes.POINTER(ctype)
        self._lib = library if isinstance(library, ctypes.CDLL) else ctypes.CDLL(str(library))
        P = code.name
        self._init = getattr(self._lib, f"{P}_init")
        self._step = getattr(self._lib, f"{P}_step")
        self._run = getattr(self._lib, f"{P}_run_record")
        self._steps = getattr(self._lib, f"{P}_run_steps")
        for fn in (self._init, self._step, self._run, self._steps):
            fn.restype = ctypes.c_int
        # stepped's: a second handle on the step taking addresses, and arrays of the state and
        # the samples allocated once, whose addresses it passes (ctypes' per-array pointer
        # objects cost more than the step), one caller at a time
        self._step_at = self._lib[f"{P}_step"]
        self._step_at.argtypes = [ctypes.c_void_p] * (5 if code.hold == "foh" else 3)
        self._step_at.restype = ctypes.c_int
        sz = code.sizes
        self._stage = (np.zeros(sz["state"], self.dtype), np.zeros(max(sz["m"], 1), self.dtype),
                       np.zeros(sz["r"], self.dtype))
        self._stage_at = tuple(a.ctypes.data for a in self._stage)
        self._stage_lock = threading.Lock()

    def _p(self, a: NDArray[Any] | None) -> Any:
        return None if a is None else a.ctypes.data_as(self._ptr)

    def _vec(self, a: ArrayLike | None, size: int) -> NDArray[Any] | None:
        if a is None:
            return None
        arr = np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(size),
                                   dtype=self.dtype)
        return arr

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None
             ) -> NDArray[Any]:
        """A new state from ``<name>_init(s, theta_hat0, x_hat0)`` (NULL: the compiled-in
        defaults).

        Parameters
        ----------
        x_hat0 : array_like, shape (n,), optional
        theta_hat0 : array_like, shape (p,), optional
            In Θ.

        Returns
        -------
        ndarray, shape (state,)
            In the generated precision.

        Raises
        ------
        ParameterSetError
            ``<name>_init`` refused θ̂₀ or x̂₀ (:attr:`Status.INIT
            <thetahat.estimation.status.Status.INIT>`: θ̂₀ outside Θ, or not finite).
        """
        s = np.zeros(self.code.sizes["state"], dtype=self.dtype)
        th, x0 = self._vec(theta_hat0, self.code.sizes["p"]), self._vec(x_hat0,
                                                                         self.code.sizes["n"])
        status = self._init(self._p(s), self._p(th), self._p(x0))
        if status != 0:
            raise status_error(Status(status), f"{self.code.name}_init refused "
                               f"theta_hat0 = {theta_hat0!r}, x_hat0 = {x_hat0!r}: "
                               f"theta_hat0 must lie in Theta and both must be finite.")
        return s

    def step(self, state: NDArray[Any], u: ArrayLike | None, y: ArrayLike,
             u_next: ArrayLike | None = None, y_next: ArrayLike | None = None) -> int:
        """``<name>_step`` on ``state`` in place; returns the status code.

        ``u_next``, ``y_next``: the next samples, which a first-order hold step takes (and
        only it).
        """
        if state.dtype != self.dtype or state.shape != (self.code.sizes["state"],):
            raise DimensionError(f"state must be a {self.dtype.__name__} vector of length "
                                 f"{self.code.sizes['state']}.")
        foh = self.code.hold == "foh"
        if foh != (y_next is not None):
            raise DimensionError(f"{self.code.name}_step takes the next samples (u_next, "
                                 "y_next) exactly when it was generated with hold='foh'.")
        m, r = self.code.sizes["m"], self.code.sizes["r"]

        def inputs(a: ArrayLike | None) -> Any:
            return self._vec(np.zeros(max(m, 1)) if a is None or m == 0 else a, max(m, 1))

        args = [self._p(inputs(u)), self._p(self._vec(y, r))]
        if foh:
            args += [self._p(inputs(u_next)), self._p(self._vec(y_next, r))]
        return int(self._step(self._p(state), *args))

    def stepped(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike
                ) -> tuple[int, NDArray[Any]]:
        """``<name>_step`` of a copy of ``state``: the status code and the stepped copy (a
        stream's step, zero-order hold; ``state`` is left as it was).

        The arrays are copied into buffers allocated once, whose addresses the C takes: a
        call costs about what :meth:`step`'s pointer conversions alone cost.

        Parameters
        ----------
        state : ndarray, shape (state,)
        u : ndarray, shape (m,), or None when m = 0
        y : ndarray, shape (r,)

        Returns
        -------
        status : int
        state : ndarray, shape (state,)
            A new array in the generated precision (the step's result; as :meth:`step`
            leaves it when the status is not 0).

        Raises
        ------
        DimensionError
            Other shapes, or a library generated with ``hold='foh'`` (use :meth:`step`).
        """
        S, U, Y = self._stage
        m = self.code.sizes["m"]
        shape_u = () if u is None else np.shape(u)
        u_ok = shape_u == (m,) if m else shape_u in ((), (0,))
        if self.code.hold == "foh" or np.shape(state) != S.shape or np.shape(y) != Y.shape \
                or not u_ok:
            raise DimensionError(f"{self.code.name}_step (stepped): a zero-order-hold step "
                                 f"takes a state of {S.shape[0]}, u of {m} and y of "
                                 f"{Y.shape[0]} values; got shapes {np.shape(state)}, "
                                 f"{shape_u}, {np.shape(y)}.")
        with self._stage_lock:
            S[:] = state
            if m:
                U[:] = u  # type: ignore[assignment]    # (a vector of m: checked above)
            Y[:] = y
            status = int(self._step_at(*self._stage_at))
            return status, S.copy()

    def _records(self, u: ArrayLike | None, y: ArrayLike, N: int
                 ) -> tuple[NDArray[Any], NDArray[Any]]:
        m, r = self.code.sizes["m"], self.code.sizes["r"]
        U = (np.zeros((N, 1)) if u is None or m == 0
             else np.asarray(u, dtype=np.float64).reshape(N, m))
        Y = np.asarray(y, dtype=np.float64).reshape(N, r)
        return (np.ascontiguousarray(U, dtype=self.dtype),
                np.ascontiguousarray(Y, dtype=self.dtype))

    def run(self, u: ArrayLike | None, y: ArrayLike, *, state0: NDArray[Any] | None = None
            ) -> CRun:
        """Record run (rows as ``observer.run`` records them), stopping at the first error."""
        Y0 = np.asarray(y)
        N = Y0.shape[0]
        U, Y = self._records(u, y, N)
        s = self.init() if state0 is None else np.array(state0, dtype=self.dtype)
        sz = self.code.sizes
        S, PHI, status, index = self.run_rows(s, U, Y)
        n, k, p = sz["n"], sz["k"], sz["p"]
        return CRun(x_hat=S[:, :n], phi_hat=PHI, theta_hat=S[:, n + k:n + k + p],
                    x_hat_refined=S[:, n + k + p:] if sz["state"] > n + k + p else None,
                    status=Status(status), index=index)

    def run_rows(self, state: NDArray[Any], U: NDArray[Any], Y: NDArray[Any],
                 out: tuple[NDArray[Any], NDArray[Any]] | None = None
                 ) -> tuple[NDArray[Any], NDArray[Any], int, int]:
        """The shim's record loop on prepared arrays: every state row, φ̂, status and index.

        Parameters
        ----------
        state : ndarray, shape (state,)
            The state before the first row, in the C precision; advanced in place (to the
            state at the last row, or where a nonzero status stopped the run).
        U : ndarray, shape (N, max(m, 1))
            C-contiguous, in the C precision (zeros when m = 0).
        Y : ndarray, shape (N, r)
            C-contiguous, in the C precision.
        out : tuple of ndarray, optional
            (S, PHI) to write into, when both are C-contiguous, in the C precision and of the
            shapes returned (e.g. row blocks of the caller's record arrays: no second copy of
            the record); otherwise new arrays. Rows after a nonzero status are not written.

        Returns
        -------
        S : ndarray, shape (N, state)
            Row i: the state at sample i (before its step): ``out[0]`` when it was used.
        PHI : ndarray, shape (N, k)
            φ̂ at sample i.
        status : int
            0, or the code (:data:`STATUS`) that stopped the run at row ``index``.
        index : int
        """
        N = Y.shape[0]
        shapes = ((N, self.code.sizes["state"]), (N, self.code.sizes["k"]))
        if out is not None and all(a.shape == shape and a.dtype == self.dtype
                                   and a.flags.c_contiguous and a.flags.writeable
                                   for a, shape in zip(out, shapes)):
            S, PHI = out
        else:
            S, PHI = (np.zeros(shape, dtype=self.dtype) for shape in shapes)
        index = ctypes.c_long(0)
        status = self._run(self._p(state), ctypes.c_long(N), self._p(U), self._p(Y),
                           self._p(S), self._p(PHI), ctypes.byref(index))
        return S, PHI, int(status), int(index.value)

    def run_steps(self, U: NDArray[Any], Y: NDArray[Any], state: NDArray[Any]) -> int:
        """N steps in one C call, nothing recorded (benchmarks); arrays in the C precision."""
        return int(self._steps(self._p(state), ctypes.c_long(Y.shape[0]), self._p(U),
                               self._p(Y)))


def load_c(code: CCode, directory: str | Path, *, flags: Sequence[str] = C_FLAGS) -> CObserver:
    """Compile ``code`` in ``directory`` (see :func:`build`) and load it.

    Parameters
    ----------
    code : CCode
    directory : str or Path
    flags : sequence of str

    Returns
    -------
    CObserver

    Examples
    --------
    >>> import tempfile
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> from thetahat.codegen import generate_c
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> obs = load_c(code, tempfile.mkdtemp()) if find_compiler() else None
    >>> obs is None or obs.step(obs.init(), [0.0], [0.1]) == 0
    True
    """
    return CObserver(code, build(code, directory, flags=flags))
