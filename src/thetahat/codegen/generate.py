"""C99 code generation for a built observer: :func:`generate_c` and its result :class:`CCode`.

The generated pair ``<name>.h``/``<name>.c`` implements the step of
:class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver` — observer (3), the update law
(8) with its projection onto Θ and excitation weight, and the second observer of Sec. VI — at a
fixed step dt with a zero- or first-order hold, in ``float`` or ``double``, with no heap, no
recursion and no global mutable state: the caller owns the state struct. The step is not
written here: it is the formulas of :mod:`~thetahat.estimation.observer.formulas` and
:mod:`~thetahat.estimation.observer.laws.formulas` printed as C (:mod:`.c_printer`, :mod:`.c_derive`),
reading the data the numba kernel reads (``compiled.kernel_arrays`` of ``observer.plan(dt)``);
g, ∂g/∂x, ∂g/∂θ, ∂g/∂y and θ* are printed from their SymPy expressions by SymPy's C99 printer
with common-subexpression elimination (:mod:`.printing`); :mod:`.c_api` writes the interface.

The state is committed only when it has not diverged (``formulas.within_bound``: its norm is
finite and at most ``DIVERGENCE_BOUND``, 1e18 in float); otherwise the step returns a status
code (:data:`.c_api.STATUS`, the codes of :class:`~thetahat.estimation.status.Status`) and
leaves the state unchanged — the C form of the status the Python step fails with. NaN in y
follows ``nan_policy``, an invalid θ* ``on_invalid``. IEEE 754 arithmetic (C99 Annex F) is
assumed, as on every target with an FPU; ``-ffast-math`` and ``-ffinite-math-only`` are
refused.

What lives here: :func:`generate_c`, its result :class:`CCode`, :func:`supports_c` and
:func:`model_hash`. What it may import: the observer and the kernel data of
:mod:`thetahat.estimation.observer` (never its back ends' run loops), the printers, interface
and harness of this package, the model and the package's helpers.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..errors import FileAccessError, UnsupportedError
from ..estimation.observer.initial_state import output_pinv
from ..estimation.observer.kernel_data import KernelParts
from ..estimation.observer.laws import (INIT_RTOL, ConstantLaw, GradientInversion,
                                        IntermittentInversion, SmoothRamp)
from ..estimation.observer.laws.theta_star import ThetaStar
from ..estimation.observer.observer import ModifiedHighGainObserver
from ..model.paramset import Box
from ..model.perturbation import SymbolicPerturbation
from ..safe_io import write_texts
from .c_api import CLayout, header_source, source_text
from .c_text import check_c_name, comment_text, name_collisions, refuse_collisions
from .c_derive import derived_step, inwards
from .harness import harness_source, makefile_source
from .printing import REALS

__all__ = ["CCode", "generate_c", "model_hash", "supports_c", "write_c_files"]

FloatArray = NDArray[np.float64]


def write_c_files(directory: str | Path, files: dict[str, str]) -> tuple[Path, ...]:
    """Write generated files (name → text) into ``directory`` as one set
    (:func:`~thetahat.safe_io.write_texts`: all written to temporary files first, then
    renamed); returns their paths.

    Parameters
    ----------
    directory : str or Path
        Created if missing.
    files : dict of str to str

    Returns
    -------
    tuple of Path

    Raises
    ------
    FileAccessError
        The directory or a file cannot be written: nothing was replaced (or, should a rename
        fail, the message lists what was).

    Examples
    --------
    >>> import pathlib, tempfile
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> [p.name for p in write_c_files(d / "c", {"a.h": "", "a.c": ""})]
    ['a.h', 'a.c']
    """
    out = Path(directory)
    try:
        return write_texts({out / fname: text for fname, text in files.items()})
    except OSError as exc:
        raise FileAccessError(f"cannot write the generated C into {out}: {exc} Choose a "
                              "writable folder with -o.") from exc

_LAWS: dict[type, str] = {ConstantLaw: "constant", IntermittentInversion: "intermittent",
         GradientInversion: "gradient"}


@dataclass(frozen=True, slots=True, repr=False)
class CCode:
    """Generated C sources of one observer (from :func:`generate_c`).

    Attributes
    ----------
    name : str
        File stem and C prefix: ``<name>.h``, ``<name>.c``, ``<name>_main.c``, ``<name>_init``...
    real : {"double", "float"}
    dt : float
        The fixed step length (s).
    header, source : str
        The dependency-free observer: ``<name>.h`` and ``<name>.c``.
    main, makefile : str
        The CSV harness ``<name>_main.c`` and the ``Makefile`` that builds ``<name>``.
    state_bytes : int
        ``sizeof(<name>_state)``: x̂, z, θ̂ (and x̂₂), all ``real``.
    const_bytes : int
        Bytes of the ``static const`` matrices and vectors of ``<name>.c``.
    sizes : dict
        (n, m, r, k, p) and the state length.
    hold : {"zoh", "foh"}
        The hold; with "foh" ``<name>_step`` also takes the next samples.
    """

    name: str
    real: str
    dt: float
    header: str
    source: str
    main: str
    makefile: str
    state_bytes: int
    const_bytes: int
    sizes: dict[str, int]
    hold: str = "zoh"

    def files(self) -> dict[str, str]:
        """File name → content of the four generated files."""
        return {f"{self.name}.h": self.header, f"{self.name}.c": self.source,
                f"{self.name}_main.c": self.main, "Makefile": self.makefile}

    def write(self, directory: str | Path) -> tuple[Path, ...]:
        """Write the four files into ``directory`` (created) as one set: all four are written
        and flushed to temporary files first, then renamed into place
        (:func:`~thetahat.safe_io.write_texts`); returns their paths.

        Raises
        ------
        FileAccessError
            The directory or a file cannot be written: nothing was replaced (or, should a
            rename fail, the message lists what was).
        """
        return write_c_files(directory, self.files())

    def summary(self) -> str:
        """One line per size, as ``thetahat codegen`` prints them."""
        word = 8 if self.real == "double" else 4
        return (f"{self.name}: n={self.sizes['n']} m={self.sizes['m']} r={self.sizes['r']} "
                f"k={self.sizes['k']} p={self.sizes['p']}, real={self.real}, dt={self.dt!r}\n"
                f"  sizeof({self.name}_state) = {self.state_bytes} bytes "
                f"({self.state_bytes // word} x {self.real})\n"
                f"  static const data         = {self.const_bytes} bytes "
                f"({self.const_bytes // word} x {self.real})")

    def __repr__(self) -> str:
        return (f"CCode(name={self.name!r}, real={self.real!r}, dt={self.dt!r}, "
                f"state_bytes={self.state_bytes}, const_bytes={self.const_bytes})")


def _theta_star(law: Any, pert: SymbolicPerturbation
                ) -> tuple[tuple[sp.Expr, ...], tuple[sp.Symbol, ...]]:
    ts = law.theta_star
    form = (ts.expr, ts.arguments) if isinstance(ts, ThetaStar) else getattr(ts, "sympy_form",
                                                                              None)
    if form is None:
        raise UnsupportedError(
            f"the θ* of the {type(law).__name__} is a Python callable "
            f"({type(law.theta_star).__name__}); C needs its SymPy form: give θ* in the model "
            "file ([estimator] theta_star), or build the law with from_perturbation.")
    exprs, args = form
    n, m, r, p, k = pert.dims
    if len(exprs) != p or len(args) != m + r + n + k:
        raise UnsupportedError(f"θ* has {len(exprs)} entries in {len(args)} arguments; expected "
                           f"p = {p} entries of col(u, y), x, φ ({m + r + n + k} arguments).")
    return tuple(exprs), tuple(args)


def _check(observer: Any, real: str) -> tuple[str, Any]:
    if not isinstance(observer, ModifiedHighGainObserver):
        raise UnsupportedError(f"generate_c needs a ModifiedHighGainObserver; got "
                           f"{type(observer).__name__}.")
    if real not in REALS:
        raise UnsupportedError(f"real must be one of {REALS}; got {real!r}.")
    pert = observer.system.perturbation
    if not isinstance(pert, SymbolicPerturbation):
        raise UnsupportedError(f"g must be a SymbolicPerturbation (C is printed from its SymPy "
                           f"form); got {type(pert).__name__}.")
    # Any: the checks below read attributes (l, M, perturbation, Gamma) of several law classes.
    law: Any = observer.update_law
    kind = _LAWS.get(type(law))
    if kind == "intermittent" and law.l is None:        # AlgebraicInversion: l ≡ 1
        kind = "algebraic"
    if kind is None:
        raise UnsupportedError(f"the update law {type(law).__name__} has no C form; supported: "
                           "ConstantLaw, AlgebraicInversion, IntermittentInversion, "
                           "GradientInversion.")
    if observer.layout.law_size:
        raise UnsupportedError(f"the update law {type(law).__name__} has a state of its own; the C "
                           "step supports memoryless laws only.")
    if not isinstance(law.parameter_set, Box):
        raise UnsupportedError(f"Θ must be a Box (its projection is a clip) for the C step; "
                           f"got {type(law.parameter_set).__name__}. A Ball or Ellipsoid Θ "
                           "runs on the numba kernel (thetahat estimate and run_estimator "
                           "choose it).")
    if getattr(law, "saturation", None) is not None:
        raise UnsupportedError("update laws with a saturation (Remark 3) have no C form yet; build "
                           "the law without saturation=.")
    if getattr(law, "layer", 0.0) != 0.0:
        raise UnsupportedError("only the hard projection (layer=0) has a C form.")
    G = np.asarray(getattr(law, "Gamma", np.eye(law.parameter_set.dim)))
    if not np.array_equal(G, np.diag(np.diag(G))):
        raise UnsupportedError("Γ must be diagonal: the Γ⁻¹-weighted projection onto a box is then "
                           "a clip (a full Γ needs a least-squares solve).")
    if kind == "intermittent" and not isinstance(law.l, SmoothRamp):
        raise UnsupportedError("the excitation weight must be smooth_ramp(low, high) of ‖φ̂‖; "
                           f"got {law.l!r}.")
    if kind == "gradient" and (law.M is not None or law.perturbation != pert):
        raise UnsupportedError("GradientInversion needs the default M = (∂g/∂θ)ᵀ and the "
                           "observer's own g.")
    return kind, law


def supports_c(observer: Any) -> bool:
    """Whether :func:`generate_c` supports the observer's parts (cheap: no SymPy printing).

    Parameters
    ----------
    observer : object
        Usually a ModifiedHighGainObserver.

    Returns
    -------
    bool

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> supports_c(build_observer(loads_model(EXAMPLE_MODEL))), supports_c(object())
    (True, False)
    """
    try:
        _check(observer, "double")
    except UnsupportedError:
        return False
    return True


def model_hash(observer: ModifiedHighGainObserver) -> str:
    """SHA-256 of what defines the observer: g and θ* (srepr), the matrices, gains, law and Θ.

    Parameters
    ----------
    observer : ModifiedHighGainObserver

    Returns
    -------
    str
        64 hexadecimal digits.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> len(model_hash(build_observer(loads_model(EXAMPLE_MODEL))))
    64
    """
    h = hashlib.sha256()
    sysm, law = observer.system, observer.update_law
    # The hash is defined for the observers generate_c supports: a SymbolicPerturbation g and a
    # Box Θ (other observers fail here with AttributeError, as before; the casts only inform mypy).
    pert = cast(SymbolicPerturbation, sysm.perturbation)
    box = cast(Box, law.parameter_set)
    h.update(sp.srepr(pert.expr).encode())
    for arr in (sysm.A, sysm.B, sysm.C, sysm.E, observer.K_x, observer.K_phi,
                box.lower, box.upper,
                np.asarray(getattr(law, "Gamma", 0.0))):
        h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    h.update(repr((type(law).__name__, getattr(law, "on_invalid", None), observer.nan_policy,
                   getattr(law, "l", None) if hasattr(getattr(law, "l", None), "low") else None
                   )).encode())
    ts = getattr(law, "theta_star", None)
    form = (ts.expr, ts.arguments) if isinstance(ts, ThetaStar) else getattr(ts, "sympy_form",
                                                                              None)
    if form is not None:
        h.update(sp.srepr(form).encode())
    if observer.second is not None:
        h.update(np.ascontiguousarray(observer.second.K_x).tobytes())
        h.update(repr(observer.second.g_on_estimates).encode())
    return h.hexdigest()


def generate_c(observer: ModifiedHighGainObserver, *, dt: float, name: str = "observer",
               real: str = "double", theta_hat0: ArrayLike | None = None,
               x_hat0: ArrayLike | None = None, eps: float | None = None,
               model_sha256: str | None = None, title: str | None = None,
               x_hat0_from_y: bool = False) -> CCode:
    """Generate a dependency-free C99 implementation of the observer's step at a fixed dt.

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        Observer (3) with its update law (8) and optional second observer (Sec. VI). Supported
        parts: a SymbolicPerturbation g; a Box Θ with diagonal Γ; ConstantLaw,
        AlgebraicInversion, IntermittentInversion (``smooth_ramp`` weight) with a θ* that has
        a SymPy form (from a model file or ``from_perturbation``), GradientInversion with the
        default M; no saturation; ``nan_policy`` "raise" or "skip"; its ``hold`` (with
        "foh" ``<name>_step`` also takes the next samples).
    dt : float
        The fixed step length (s) > 0.
    name : str
        File stem and C prefix: a C identifier that the generated code may use as a prefix
        (:func:`~thetahat.codegen.c_text.check_c_name`: ASCII, starting with a letter, at most
        24 characters, no ``__``, no keyword or reserved name, and no identifier of the
        generated code's own starting with ``<name>_``).
    real : {"double", "float"}
        The C type of every number (``<name>_real_t``).
    theta_hat0, x_hat0 : array_like, optional
        Defaults compiled in for ``<name>_init(s, NULL, NULL)``: ``update_law.init()`` and 0.
    eps : float, optional
        ε the gains were designed at, recorded in the header comment.
    model_sha256 : str, optional
        Hash recorded in the header (default :func:`model_hash` of the observer; the command
        line passes the model file's).
    title : str, optional
        Model title for the header comment (made safe for a comment:
        :func:`~thetahat.codegen.c_text.comment_text`).
    x_hat0_from_y : bool
        The harness starts x̂ at x̂₀ + C⁺(y(0) − C x̂₀) (``<name>_start_from_y`` on its first
        sample), as :func:`~thetahat.modelfile.start_x_hat` does for a model file's estimators;
        default False: at x̂₀. The library always offers ``<name>_start_from_y``.

    Returns
    -------
    CCode

    Raises
    ------
    UnsupportedError
        A part of the observer has no C form (the message names it).
    OptionError
        ``name`` cannot name generated C (the message says why and names one that can).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> sorted(code.files())
    ['Makefile', 'prop3.c', 'prop3.h', 'prop3_main.c']
    >>> code.state_bytes                      # x̂ (2), z (1), θ̂ (1), x̂₂ (2) doubles
    48
    """
    prefix = check_c_name(name)
    kind, law = _check(observer, real)
    hold = observer.hold
    h = _step_length(dt, real)
    pert = cast(SymbolicPerturbation, observer.system.perturbation)     # _check verified it
    n, m, r, p, k = pert.dims
    ts = _theta_star(law, pert) if kind in ("algebraic", "intermittent") else None
    lay = CLayout(prefix=prefix, real=real, dims=(n, m, r, k, p),
                  second=observer.second is not None, skip=observer.nan_policy == "skip",
                  foh=hold == "foh")
    step = _derive(observer, kind, law, lay, h, ts, theta_hat0, x_hat0)
    info = _info(observer, law, h, hold, real, ts is not None, eps=eps,
                 model_sha256=model_sha256, title=title)
    header = header_source(lay, _banner(f"{prefix}.h", info, "interface"))
    source = source_text(lay, _banner(f"{prefix}.c", info,
                                      "implementation (C99, <math.h> only, no heap)"), step)
    names = {"u": [s.name for s in pert.u], "y": [s.name for s in pert.y],
             "x": [s.name for s in pert.x], "theta": [s.name for s in pert.theta]}
    word = 8 if real == "double" else 4
    main = harness_source(prefix, names, k, real, lay.second, h, lay.foh,
                          start_from_y=x_hat0_from_y)
    refuse_collisions(prefix, name_collisions(prefix, header, [source, main]))
    return CCode(name=prefix, real=real, dt=h, header=header, source=source, main=main,
                 makefile=makefile_source(prefix), state_bytes=lay.size * word,
                 const_bytes=step.const_count * word,
                 sizes={"n": n, "m": m, "r": r, "k": k, "p": p, "state": lay.size},
                 hold=hold)


def _derive(observer: ModifiedHighGainObserver, kind: str, law: Any, lay: CLayout, h: float,
            ts: tuple[tuple[sp.Expr, ...], tuple[sp.Symbol, ...]] | None,
            theta_hat0: ArrayLike | None, x_hat0: ArrayLike | None) -> Any:
    """The step printed as C (:func:`~thetahat.codegen.c_derive.derived_step`) with the data
    it reads: Θ's box (moved inwards in float), θ̂₀, x̂₀, C and C⁺."""
    n, _, _, _, p = lay.dims
    C = observer.system.C
    th0 = np.asarray(law.init(theta_hat0), dtype=np.float64).reshape(p)
    x0 = np.zeros(n) if x_hat0 is None else np.asarray(x_hat0, dtype=np.float64).reshape(n)
    code = {"constant": 0, "algebraic": 1, "intermittent": 2, "gradient": 3}[kind]
    ramp = (float(law.l.low), float(law.l.high)) if kind == "intermittent" else None
    box = cast(Box, law.parameter_set)
    parts = KernelParts(code=code, perturbation=cast(SymbolicPerturbation,
                                                     observer.system.perturbation),
                        theta_set=box, ramp=ramp,
                        freeze=getattr(law, "on_invalid", "") == "freeze")
    lower, upper = box.lower, box.upper
    if lay.real == "float":
        lower, upper = inwards(lower, upper)
    extra = {"THETA_LOWER": lower, "THETA_UPPER": upper, "THETA_HAT0": th0, "X_HAT0": x0,
             "INIT_RTOL": INIT_RTOL, "OUT_C": C, "OUT_CPINV": output_pinv(C)}
    return derived_step(parts, observer.plan(h), prefix=lay.prefix, real=lay.real,
                        foh=lay.foh, skip=lay.skip, dt=h, theta_star=ts, extra=extra)


def _info(observer: ModifiedHighGainObserver, law: Any, h: float, hold: str, real: str,
          theta_star: bool, *, eps: float | None, model_sha256: str | None,
          title: str | None) -> dict[str, str]:
    """What the banner of the generated files records."""
    from .._version import __version__

    second = observer.second
    return {
        "model": title or "observer", "sha256": model_sha256 or model_hash(observer),
        "eps": "not recorded" if eps is None else repr(float(eps)), "dt": repr(h),
        "hold": hold, "law": type(law).__name__,
        "policy": (f"y NaN -> {observer.nan_policy}"
                   + (f"; theta* invalid -> {law.on_invalid}" if theta_star else "")),
        "second": "none" if second is None else
        f"Sec. VI, g on {'estimates' if second.g_on_estimates else 'y'}",
        "real": real, "version": __version__}


def _step_length(dt: Any, real: str) -> float:
    """dt as a float that the C type ``real`` holds as a normal number (else refused)."""
    try:
        h = float(dt)
    except (TypeError, ValueError):
        h = math.nan
    if not (math.isfinite(h) and h > 0):
        raise UnsupportedError(f"dt must be a finite step length > 0; got {dt!r}.")
    kind = np.float64 if real == "double" else np.float32
    info = np.finfo(kind)
    if not (float(info.tiny) <= h <= float(info.max)):
        raise UnsupportedError(f"dt = {h!r} is not a normal {real} (the range is "
                               f"[{float(info.tiny):.3g}, {float(info.max):.3g}]): the "
                               f"generated DT would be 0 or inf; choose another dt, or "
                               f"--real double.")
    return h


def _banner(name: str, info: dict[str, str], what: str) -> str:
    """The comment at the top of a generated file: every value made safe for a comment."""
    info = {key: comment_text(value) for key, value in info.items()}
    return (f"/* {name} -- {what}\n"
            f" * Generated by thetahat {info['version']} (thetahat codegen); do not edit.\n *\n"
            " * The modified high-gain observer (3) with update law (8) of Grip, Saberi &\n"
            " * Johansen, discretised at a fixed step (exact exponential of the linear part,\n"
            " * linearly implicit correction for g).\n"
            f" *   model:      {info['model']}\n"
            f" *   sha256:     {info['sha256']}\n"
            f" *   eps:        {info['eps']}\n"
            f" *   dt:         {info['dt']} s\n"
            f" *   hold:       {info['hold']}\n"
            f" *   law:        {info['law']} (projection onto the box Theta)\n"
            f" *   second:     {info['second']}\n"
            f" *   policy:     {info['policy']}\n"
            f" *   real:       {info['real']}\n"
            f" *   thetahat:   {info['version']}\n */\n")
