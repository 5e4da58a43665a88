"""The joint EKF on col(x, θ) as dependency-free C99: stage 2's kernels printed for a controller.

:func:`generate_ekf_c` prints one sample of :class:`~thetahat.estimation.statistical.ekf.JointEKF`
— the kernels :func:`~thetahat.estimation.statistical.ekf_kernels.ekf_predict` and
:func:`~thetahat.estimation.statistical.ekf_kernels.ekf_update` with what they call (the RK4
sub-steps of :func:`~thetahat.estimation.statistical.plant_kernel.propagate`, the hold, the
Joseph update, θ̂ clipped to Θ) — with the C printer of the observer's formulas
(:class:`~thetahat.codegen.c_printer.CUnit`), specialised for the model: every shape, the step
length, the hold and the sub-steps' floor are fixed when the C is printed, every work array
is a fixed-size local (no heap, nothing from libc but ``<math.h>``). The model's f, ∂f/∂x and
∂f/∂θ are the SymPy forms the Python kernels print
(:func:`~thetahat.estimation.statistical.plant_forms.plant_jacobians`), printed by SymPy's C99
printer (:func:`~thetahat.codegen.printing.c_function`).

The C keeps what :meth:`JointEKF.step <thetahat.estimation.statistical.ekf.JointEKF.step>`
does per sample: no prediction at the first sample; NaN in y is predicted over (no update);
NaN or inf in u and inf in y are refused (``<NAME>_NONFINITE_INPUT``, the state untouched);
a state or covariance diagonal that is no longer finite is ``<NAME>_DIVERGED``.

The holds it prints are a stream's causal ones: ``"zoh"`` (u held from each sample),
``"foh"`` (u on the line from the previous sample to the current one, which the step has: the
state keeps the previous u, as :meth:`JointEKF.step` does) and ``"smooth"`` (the line through
the corrected samples ũ: :func:`~thetahat.estimation.statistical.input_hold.smooth_step`
printed, its history of three samples and two sums in the state; :func:`input_samples`).
What it cannot do (refused, :class:`~thetahat.errors.UnsupportedError`): the band-limited
hold (it reads later samples); a Θ other than a box; ``float``; an unknown σ (give
``noise_std``: the stream's estimate from its first samples is not generated).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import OptionError, UnsupportedError
from ..estimation.kernels.subset import source_tree
from ..estimation.statistical import ekf_kernels as ek
from ..estimation.statistical import plant_kernel as pk
from ..estimation.statistical.ekf import JointEKF
from ..estimation.statistical.input_hold import HISTORY, smooth_step
from ..estimation.statistical.plant_forms import plant_jacobians
from ..estimation.statistical.stage2_set import clip_kernel, stage2_set
from ..model.paramset import Box
from .c_printer import CUnit
from .c_text import check_c_name, comment_text
from .c_values import Arr, Const, Scal
from .ekf_c_text import ekf_header, ekf_main, ekf_source
from .generate import write_c_files
from .harness import makefile_source
from .printing import c_function

__all__ = ["C_HOLDS", "EKFCode", "KERNELS", "KERNEL_GLOBALS", "c_array", "check_stage2",
           "generate_ekf_c", "input_samples"]

#: The holds of stage 2 the C prints: a stream's causal ones, whose u over the interval from
#: the previous sample reads that sample and the current one (the step's state keeps the
#: previous u, and for "smooth" the history its correction needs).
C_HOLDS = ("zoh", "foh", "smooth")

#: The kernels printed, by the names the others call them (the guarded C prints them too).
KERNELS = {"ekf_predict": ek.ekf_predict, "ekf_update": ek.ekf_update,
            "ekf_gain": ek.ekf_gain, "ekf_joseph": ek.ekf_joseph,
            "propagate": pk.propagate, "propagate_into": pk.propagate_into,
            "stage_jac": pk.stage_jac, "held_input": pk.held_input,
            "balanced_radius": pk.balanced_radius,
            "project": clip_kernel, "smooth_step": smooth_step}
#: The module constants the printed kernels read, as the printer's constants.
KERNEL_GLOBALS = {**{k: Const(v) for k, v in pk.KERNEL_CONSTANTS.items()},
                  "HISTORY": Const(HISTORY)}


def input_samples(unit: CUnit, m: int, hold: str, state: str) -> str:
    """C statements that set ``Ut[]``, the samples stage 2 reads, from the raw ``u[]``.

    Under ``"smooth"`` the corrected samples ũ of the printed
    :func:`~thetahat.estimation.statistical.input_hold.smooth_step`, its history in
    ``state->u_hist`` (the last three samples) and ``state->u_sums`` (the two sums), advanced;
    the raw samples otherwise. The caller declares ``Ut`` and ``Raw`` (``max(m, 1)`` reals)
    and ``i``.

    Parameters
    ----------
    unit : CUnit
        The printer holding the kernels (:data:`KERNELS`).
    m : int
        Inputs.
    hold : str
        Stage 2's hold.
    state : str
        The C expression of the state pointer whose history is read and advanced.

    Returns
    -------
    str
    """
    copy = f"for (i = 0; i < {m}; ++i) Ut[i] = u[i];"
    if hold != "smooth" or m == 0:
        return copy
    call = unit.call("smooth_step", [
        Arr("Raw", (m,)), Arr(f"{state}->u_hist", (HISTORY * m,)),
        Arr(f"{state}->u_sums", (2 * m,)),
        Scal(f"({state}->k < {HISTORY} ? (int){state}->k : {HISTORY})", "int"), Const(m),
        Arr("Ut", (m,))])
    return (f"for (i = 0; i < {m}; ++i) Raw[i] = u[i];\n    "
            f"{call.name}({', '.join(call.args)});")


@dataclass(frozen=True, slots=True, repr=False)
class EKFCode:
    """The generated C of one joint EKF (from :func:`generate_ekf_c`).

    Attributes
    ----------
    name : str
        File stem and C prefix (``<name>.h``, ``<name>_init``, ``<name>_step``).
    dt : float
        The fixed sampling interval (s).
    header, source : str
        ``<name>.h`` and ``<name>.c``: the filter (C99, ``<math.h>`` only).
    main, makefile : str
        The CSV harness ``<name>_main.c`` (reads ``t,u…,y…`` rows, writes ``t,x̂…,θ̂…``)
        and the ``Makefile`` that builds ``<name>``.
    sizes : dict
        n, m, r, p and the hold and sub-step floor.
    """

    name: str
    dt: float
    header: str
    source: str
    main: str
    makefile: str
    sizes: dict[str, Any]

    def files(self) -> dict[str, str]:
        """File name → content of the four generated files."""
        return {f"{self.name}.h": self.header, f"{self.name}.c": self.source,
                f"{self.name}_main.c": self.main, "Makefile": self.makefile}

    def write(self, directory: str | Path) -> tuple[Path, ...]:
        """Write the four files into ``directory`` as one set
        (:func:`~thetahat.safe_io.write_texts`); returns their paths.

        Raises
        ------
        FileAccessError
            Nothing was replaced (or the message lists what was).
        """
        return write_c_files(directory, self.files())

    def summary(self) -> str:
        """What ``thetahat codegen --method ekf`` prints."""
        s = self.sizes
        N = s["n"] + s["p"]
        return (f"{self.name}: joint EKF, n={s['n']} m={s['m']} r={s['r']} p={s['p']}, "
                f"dt={self.dt!r}, hold={s['hold']}, RK4 sub-steps >= {s['substeps']}\n"
                f"  {self.name}_state: {N + N * N + max(s['m'], 1)} x double (s, P, u_prev) "
                "and a long (k)")

    def __repr__(self) -> str:
        return f"EKFCode(name={self.name!r}, dt={self.dt!r}, sizes={self.sizes})"


def check_stage2(ekf: Any, dt: float, what: str = "the C EKF") -> None:
    """Refuse what the printed stage 2 cannot do (``what`` names the C in the messages).

    Parameters
    ----------
    ekf : JointEKF
        Stage 2 as the C would run it.
    dt : float
    what : str

    Raises
    ------
    UnsupportedError
        Not a JointEKF, a hold not in :data:`C_HOLDS` (``"bandlimited"``), a Θ other than a box,
        p = 0 or r = 0.
    OptionError
        No ``noise_std``; a ``dt`` that is not a finite number > 0.
    """
    if not isinstance(ekf, JointEKF):
        raise UnsupportedError(f"generate_ekf_c needs a JointEKF; got {type(ekf).__name__}.")
    if ekf.hold not in C_HOLDS:
        raise UnsupportedError(
            f"{what} has the causal holds {', '.join(map(repr, C_HOLDS))}; got {ekf.hold!r} "
            "('bandlimited' reads later samples). Use hold='zoh' for a DAC's input, else "
            "'smooth' or 'foh' (--hold).")
    theta_set = ekf.system.require_parameter_set(what)
    if not isinstance(theta_set, Box):
        raise UnsupportedError(f"{what} keeps θ̂ in a box Θ only; got {theta_set!r}. "
                               "Give Θ as bounds (a Box).")
    if ekf.noise_std is None:
        raise OptionError(f"{what} needs the output noise σ (R = σ² I) when it is "
                          "generated: give noise_std (--noise-std, or --data LOG to estimate "
                          "it from a record).")
    if ekf.system.p == 0 or ekf.system.r == 0:
        raise UnsupportedError(f"{what} needs p ≥ 1 parameters and r ≥ 1 outputs.")
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
        raise OptionError(f"dt must be a finite number > 0; got {dt!r}.")


def c_array(name: str, values: Any) -> str:
    """``static const real_t NAME[size] = {…};`` of finite ``values``, flattened row-major.

    Parameters
    ----------
    name : str
    values : array_like

    Returns
    -------
    str

    Raises
    ------
    UnsupportedError
        A value is not finite.

    Examples
    --------
    >>> c_array("S0", [1.0, 0.5])
    'static const real_t S0[2] = {1.0, 0.5};'
    """
    flat = np.asarray(values, dtype=np.float64).ravel()
    if not np.all(np.isfinite(flat)):
        raise UnsupportedError(f"{name} has non-finite entries; the generated C needs finite data.")
    body = ", ".join(repr(float(v)) for v in flat) if flat.size else "0.0"
    return f"static const real_t {name}[{max(flat.size, 1)}] = {{{body}}};"


def generate_ekf_c(ekf: JointEKF, *, dt: float, name: str = "ekf",
                   x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None,
                   title: str = "") -> EKFCode:
    """Print one sample of a joint EKF as C99 for a fixed sampling interval.

    Parameters
    ----------
    ekf : JointEKF
        With ``noise_std`` given, ``hold`` ``"zoh"`` or ``"foh"`` and a box Θ; its ``q_x``,
        ``theta_sd``, ``x_sd``, ``h_rho`` and ``substeps`` (default 1, as
        :meth:`JointEKF.step`) are printed into the C.
    dt : float
        The sampling interval (s): the prediction's length.
    name : str
        File stem and C prefix, a C identifier
        (:func:`~thetahat.codegen.c_text.check_c_name`).
    x_hat0, theta_hat0 : array_like, optional
        The prior means of ``<name>_init`` (:meth:`JointEKF.init`; θ̂₀ in Θ).
    title : str
        A line for the files' banner (a comment: any text is safe).

    Returns
    -------
    EKFCode
        Run ``<name>_init`` once, then ``<name>_step(&st, u, y)`` per sample: ``st.s`` is
        col(x̂, θ̂) after the sample, as ``JointEKF.step`` gives it.

    Raises
    ------
    UnsupportedError
        A hold other than ``"zoh"`` or ``"foh"``, a Θ other than a box, or a part with no
        C form.
    OptionError
        No ``noise_std``, a bad ``dt`` or ``name``.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import JointEKF
    >>> ekf = JointEKF(system=lugre.system(), noise_std=0.02, hold="zoh", compiled=False)
    >>> code = generate_ekf_c(ekf, dt=1e-3, name="lugre_ekf")
    >>> "int lugre_ekf_step(lugre_ekf_state *st" in code.source
    True
    """
    check_stage2(ekf, dt)
    name = check_c_name(name)
    sys_ = ekf.system
    n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
    s0, P0 = ekf.prior(x_hat0=x_hat0, theta_hat0=theta_hat0)
    sigma = np.asarray(ekf.init().noise_std, dtype=np.float64)
    theta_set = stage2_set(sys_.require_parameter_set("the C EKF"))
    substeps = ekf.substeps or 1
    pc, WT = pk.Propagation(hold=ekf.hold, substeps=substeps, h_rho=ekf.h_rho).arrays()
    data = {"C_OUT": np.asarray(sys_.C, dtype=np.float64),
            "Q_X": ekf.q_x * np.eye(n), "R_NOISE": np.diag(sigma ** 2),
            "THETA_LO": theta_set.lo, "THETA_HI": theta_set.hi,
            "THETA_ELL": np.zeros((p + 1, p)), "S0": s0, "P0": P0}
    shapes = {k: np.shape(v) for k, v in data.items()}
    unit = CUnit({k: source_tree(fn) for k, fn in KERNELS.items()},
                 {"C_OUT": Arr("C_OUT", shapes["C_OUT"], True), **KERNEL_GLOBALS},
                 lambda fname, args: (("rhs_jac", [a.name for a in args or ()])
                                      if fname == "rhs_jac" else None), "double")
    N = n + p
    glob = {k: Arr(k, shapes[k], True) for k in ("Q_X", "R_NOISE", "THETA_LO", "THETA_HI",
                                                 "THETA_ELL")}
    predict = unit.call("ekf_predict", [
        Arr("st->s", (N,)), Arr("st->P", (N, N)), Arr("U", (2, m)), Const(0), Const(float(dt)),
        tuple(Const(float(v)) for v in pc), Arr("WT", WT.shape), glob["Q_X"],
        Arr("Phi", (n, n)), Arr("Gam", (n, p))])
    update = unit.call("ekf_update", [
        Arr("st->s", (N,)), Arr("st->P", (N, N)), Arr("Y", (r,)), glob["R_NOISE"],
        glob["THETA_LO"], glob["THETA_HI"], glob["THETA_ELL"]])
    samples = input_samples(unit, m, ekf.hold, "st")
    if unit.written_globals:
        raise UnsupportedError(f"the EKF kernels write {sorted(unit.written_globals)}")
    xs, us, ts, f, Fx, Ft = plant_jacobians(sys_)
    rhs = c_function("rhs_jac", [("x", xs), ("u", us), ("th", ts)],
                     [("f", f), ("Fx", Fx), ("Ft", Ft)], "double")
    kernels = unit.source()
    consts = [c_array(k, v) for k, v in data.items()
              if k in ("S0", "P0") or k in kernels or k in rhs]
    sizes = {"n": n, "m": m, "r": r, "p": p, "hold": ekf.hold, "substeps": substeps}
    banner = _banner(name, title, dt, substeps, ekf)
    source = ekf_source(name, banner, consts, rhs, kernels,
                        predict=f"{predict.name}({', '.join(predict.args)})",
                        update=f"{update.name}({', '.join(update.args)})", samples=samples,
                        sizes=sizes)
    return EKFCode(name=name, dt=float(dt), header=ekf_header(name, banner, sizes),
                   source=source, main=ekf_main(name, banner, sizes),
                   makefile=makefile_source(name), sizes=sizes)


def _banner(name: str, title: str, dt: float, substeps: int, ekf: JointEKF) -> str:
    lines = [f"{name}: the joint EKF on col(x, theta) of thetahat (stage 2), one sample per "
             "call.", comment_text(title) if title else "",
             f"dt = {dt!r} s, hold {ekf.hold}, RK4 sub-steps >= {substeps} (h*rho <= "
             f"{ekf.h_rho!r}),"
             f" q_x = {ekf.q_x!r}.",
             "Generated by thetahat codegen --method ekf; do not edit."]
    return "/*\n" + "".join(f" * {line}\n" for line in lines if line) + " */\n"
