"""The guarded estimator as dependency-free C99: stage 1, stage 2 and the guard on a controller.

:func:`generate_guarded_c` prints one sample of
:meth:`GuardedEstimator.step <thetahat.estimation.statistical.guarded.GuardedEstimator.step>`
without re-anchoring fits, as two translation units:

* ``<name>_stage1.c`` — the paper's observer with its update law, printed by
  :func:`~thetahat.codegen.generate.generate_c` (Theorem 1's guarantee, θ̂_G);
* ``<name>.c`` — stage 2 and the guard: the very loop the Python estimator runs,
  :func:`~thetahat.estimation.statistical.guard.guarded_loop`, printed over the joint EKF's
  kernels (:mod:`~thetahat.estimation.statistical.ekf_kernels`, as
  :func:`~thetahat.codegen.ekf_c.generate_ekf_c` prints them) by the C printer of the
  observer's formulas (:class:`~thetahat.codegen.c_printer.CUnit`), with f, ∂f/∂x, ∂f/∂θ
  from the same SymPy forms.

Per sample ``<name>_step`` reads stage 1's θ̂_G and x̂ at the current sample, runs the guard's
loop for that sample (the EKF's prediction from the previous sample, its update, the band δ,
the clip of θ̂₂ to θ̂_G ± δ, Π_Θ, the reset of stage 2 from a settled stage 1), then advances
stage 1. Every shape, the step length, the hold, the sub-steps and the guard's constants are
fixed when the C is printed; the state is a fixed-size struct (no heap, nothing from libc but
``<math.h>``), and a step costs the same at sample 10 and at sample 10⁹: the C keeps no record.

What it does not do (refused, :class:`~thetahat.errors.UnsupportedError` /
:class:`~thetahat.errors.OptionError`): the MAP fits that re-anchor stage 2 (each fits all the
data so far: memory and time grow with the record; build the estimator with
``use_fits=False``, whose Python ``step`` and ``run`` are the C's reference); stage 2's
``"bandlimited"`` hold and a Θ other than a box (as the C EKF, which prints the causal holds
``"zoh"``, ``"foh"`` and ``"smooth"``); an unknown σ. Stage 1 steps with the raw samples
held, whatever the observer's ``run`` hold, as :meth:`GuardedEstimator.step` has it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import OptionError, UnsupportedError
from ..estimation.kernels.subset import source_tree
from ..estimation.observer.observer import ModifiedHighGainObserver
from ..estimation.statistical import guard as gd
from ..estimation.statistical import plant_kernel as pk
from ..estimation.statistical.common import joint_prior
from ..estimation.statistical.ekf import JointEKF
from ..estimation.statistical.guarded import GuardedEstimator
from ..estimation.statistical.plant_forms import plant_jacobians
from ..estimation.statistical.stage2_set import stage2_set
from .c_printer import CUnit
from .c_text import check_c_name, comment_text
from .c_values import INT, Arr, Const, Scal
from .ekf_c import KERNEL_GLOBALS, KERNELS, c_array, check_stage2, input_samples
from .generate import CCode, generate_c, write_c_files
from .guarded_c_text import guarded_header, guarded_main, guarded_makefile, guarded_source
from .printing import c_function

__all__ = ["GuardedCode", "generate_guarded_c"]

#: The functions printed besides the EKF's kernels, by the names the loop calls them.
_GUARD = {"guarded_loop": gd.guarded_loop, "progress_reset": gd.progress_reset,
          "apply_fit": gd.apply_fit,
          "progress_step": gd.progress_step, "band": gd.band,
          "reset_stage2": gd.reset_stage2}


@dataclass(frozen=True, slots=True, repr=False)
class GuardedCode:
    """The generated C of one guarded estimator (from :func:`generate_guarded_c`).

    Attributes
    ----------
    name : str
        File stem and C prefix (``<name>.h``, ``<name>_init``, ``<name>_step``).
    dt : float
        The fixed sampling interval (s).
    stage1 : CCode
        Stage 1, the paper's observer (``<name>_stage1.h``, ``<name>_stage1.c``).
    header, source : str
        ``<name>.h`` and ``<name>.c``: stage 2 and the guard (C99, ``<math.h>`` only).
    main, makefile : str
        The CSV harness ``<name>_main.c`` (reads ``t,u…,y…`` rows, writes
        ``t,x̂…,θ̂…,θ̂_G…,θ̂₂…,δ…``) and the ``Makefile`` that builds ``<name>``.
    sizes : dict
        n, m, r, p, the hold, the sub-step floor, stage 1's x̂ accessor and ``state_doubles``
        (the doubles of ``<name>_state``, stage 1's included).
    """

    name: str
    dt: float
    stage1: CCode
    header: str
    source: str
    main: str
    makefile: str
    sizes: dict[str, Any]

    def files(self) -> dict[str, str]:
        """File name → content of the six generated files."""
        return {f"{self.stage1.name}.h": self.stage1.header,
                f"{self.stage1.name}.c": self.stage1.source,
                f"{self.name}.h": self.header, f"{self.name}.c": self.source,
                f"{self.name}_main.c": self.main, "Makefile": self.makefile}

    def write(self, directory: str | Path) -> tuple[Path, ...]:
        """Write the six files into ``directory`` as one set
        (:func:`~thetahat.safe_io.write_texts`); returns their paths.

        Raises
        ------
        FileAccessError
            Nothing was replaced (or the message lists what was).
        """
        return write_c_files(directory, self.files())

    def summary(self) -> str:
        """What ``thetahat codegen --method guarded`` prints."""
        s = self.sizes
        return (f"{self.name}: guarded estimator (stage 1 the paper's observer, stage 2 the "
                f"joint EKF, the guard; no fits), n={s['n']} m={s['m']} r={s['r']} "
                f"p={s['p']}, dt={self.dt!r}, hold={s['hold']}, RK4 sub-steps >= "
                f"{s['substeps']}\n  {self.name}_state: {s['state_doubles']} x double, 3 int "
                "and a long, fixed: memory and time per step do not grow with the record")

    def __repr__(self) -> str:
        return f"GuardedCode(name={self.name!r}, dt={self.dt!r}, sizes={self.sizes})"


def _observer(stage1: Any) -> ModifiedHighGainObserver:
    """Stage 1 as the observer the C generator prints (a compiled one's source observer),
    with the zero-order hold of a stream's step (:meth:`GuardedEstimator.step` advances stage
    1 by its ``step``, which holds the current samples whatever the observer's ``run`` hold)."""
    obs = getattr(stage1, "observer", stage1)
    if not isinstance(obs, ModifiedHighGainObserver):
        raise UnsupportedError(f"the guarded C prints the paper's observer as stage 1; got "
                               f"{type(stage1).__name__}.")
    return obs.with_run_options(hold="zoh")


def _check(est: Any, dt: float) -> None:
    if not isinstance(est, GuardedEstimator):
        raise UnsupportedError(f"generate_guarded_c needs a GuardedEstimator; got "
                               f"{type(est).__name__}.")
    if est.use_fits:
        raise OptionError(
            "the guarded C runs no re-anchoring fits (each fits all the data so far: memory "
            "and time that grow with the record); build the estimator with use_fits=False "
            "(its Python step and run are what the C computes).")
    if est.window is not None:
        raise OptionError("window bounds the fits, which the guarded C does not run: give "
                          "window=None.")
    check_stage2(JointEKF(system=est.model, noise_std=est.noise_std, hold=est.hold,
                          q_x=est.q_x, compiled=False), dt, "the guarded C")


def generate_guarded_c(est: GuardedEstimator, *, dt: float, name: str = "guarded",
                       x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None,
                       eps: float | None = None, title: str = "") -> GuardedCode:
    """Print one sample of a guarded estimator without fits as C99 for a fixed sampling
    interval.

    Parameters
    ----------
    est : GuardedEstimator
        With ``use_fits=False``, ``noise_std`` given, ``hold`` ``"zoh"`` or ``"foh"`` (stage
        2's) and a box Θ; stage 1 (its ``stage1``) an observer
        :func:`~thetahat.codegen.generate.generate_c` prints;
        its ``q_x``, ``x_sd``, ``h_rho``, ``substeps`` (default 1, as :meth:`GuardedEstimator.step`)
        and the guard's constants are printed into the C.
    dt : float
        The sampling interval (s).
    name : str
        File stem and C prefix, a C identifier (stage 1 is ``<name>_stage1``).
    x_hat0, theta_hat0 : array_like, optional
        The start values of ``<name>_init`` (:meth:`GuardedEstimator.init`; θ̂₀ in Θ).
    eps : float, optional
        ε, for stage 1's banner.
    title : str
        A line for the files' banner (a comment: any text is safe).

    Returns
    -------
    GuardedCode
        Run ``<name>_init`` once, then ``<name>_step(&st, u, y)`` per sample: ``st.theta_hat``
        is the guarded θ̂ and ``st.x_hat`` stage 2's x̂ at that sample, as
        :meth:`GuardedEstimator.step` gives them.

    Raises
    ------
    OptionError
        Fits on, no ``noise_std``, a bad ``dt`` or ``name``.
    UnsupportedError
        A hold other than ``"zoh"`` or ``"foh"``, a Θ other than a box, or a part with no
        C form.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.guarded import GuardedEstimator
    >>> obs = lugre.observer()
    >>> est = GuardedEstimator(stage1=obs, noise_std=0.02, hold="zoh", use_fits=False,
    ...                        compiled=False)
    >>> code = generate_guarded_c(est, dt=1e-3, name="lg")
    >>> sorted(code.files())
    ['Makefile', 'lg.c', 'lg.h', 'lg_main.c', 'lg_stage1.c', 'lg_stage1.h']
    """
    _check(est, dt)
    name = check_c_name(name)
    sys_ = est.model
    n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
    N = n + p
    start = est.init(x_hat0=x_hat0, theta_hat0=theta_hat0)
    x0, th0 = start.x_hat0, start.theta_hat0
    stage1 = generate_c(_observer(est.stage1), dt=dt, name=f"{name}_stage1",
                        theta_hat0=th0, x_hat0=x0, eps=eps, title=title or None)
    s0, P0 = joint_prior(sys_, x0, th0, x_sd=est.x_sd)      # stage 2's prior, as the stream's
    sigma = np.broadcast_to(np.asarray(est.noise_std, dtype=np.float64), (r,))
    theta_set = stage2_set(sys_.require_parameter_set("the guarded C"))
    substeps = est.substeps or 1
    pc, WT = pk.Propagation(hold=est.hold, substeps=substeps, h_rho=est.h_rho).arrays()
    cfg = np.concatenate([[est.kappa, est.c, est.rho_max, est.dwell],
                          np.sqrt(np.diag(P0)[n:]), np.zeros(p), np.full(p, -1.0)])
    data = {"C_OUT": np.asarray(sys_.C, dtype=np.float64), "Q_X": est.q_x * np.eye(n),
            "R_NOISE": np.diag(sigma ** 2), "THETA_LO": theta_set.lo,
            "THETA_HI": theta_set.hi, "THETA_ELL": np.zeros((p + 1, p)), "S0": s0,
            "P0": P0, "CFG": cfg, "WT": WT}
    shapes = {k: np.shape(v) for k, v in data.items()}
    funcs = {k: source_tree(fn) for k, fn in KERNELS.items()}
    funcs.update({"predict": funcs["ekf_predict"], "update": funcs["ekf_update"]})
    funcs.update({k: source_tree(fn) for k, fn in _GUARD.items()})
    unit = CUnit(funcs,
                 {"C_OUT": Arr("C_OUT", shapes["C_OUT"], True), **KERNEL_GLOBALS,
                  "NIS_WINDOW": Const(gd.NIS_WINDOW)},
                 lambda fname, args: (("rhs_jac", [a.name for a in args or ()])
                                      if fname == "rhs_jac" else None), "double")
    glob = {k: Arr(k, shapes[k], True) for k in data if k not in ("S0",)}
    rows = 2
    loop = unit.call("guarded_loop", [
        Arr("w->s", (N,)), Arr("w->P", (N, N)), glob["P0"], Arr("U", (rows, m)),
        Arr("Y", (rows, r)), Arr("tt", (rows,)), Scal("k0", INT), Scal("k0 + 1", INT),
        Scal("koff", INT), Arr("w->R", (r, r)), glob["THETA_LO"], glob["THETA_HI"],
        glob["THETA_ELL"], tuple(Const(float(v)) for v in pc), glob["WT"], glob["Q_X"],
        Arr("THG", (rows, p)), Arr("XG", (rows, n)), Arr("w->pst", (p, 6)),
        Arr("w->gst", (3,)), Arr("w->cfg", cfg.shape), Arr("TH", (rows, p)),
        Arr("TH2", (rows, p)),
        Arr("X2", (rows, n)), Arr("SD2", (rows, p)), Arr("BAND", (rows, p)),
        Arr("CLIP", (rows,)), Arr("RESET", (rows,)), Arr("NIS", (rows,))])
    init = unit.call("progress_reset", [Arr("w->pst", (p, 6)), Arr("THG", (p,))])
    fit = unit.call("apply_fit", [Arr("w->s", (N,)), Arr("w->P", (N, N)),
                                  Arr("w->R", (r, r)), Arr("w->cfg", cfg.shape),
                                  Arr("TF", (p,)), Arr("CF", (p, p)), Arr("SF", (r,))])
    samples = input_samples(unit, m, est.hold, "w")
    if unit.written_globals:
        raise UnsupportedError(f"the guard's kernels write {sorted(unit.written_globals)}")
    xs, us, ts, f, Fx, Ft = plant_jacobians(sys_)
    rhs = c_function("rhs_jac", [("x", xs), ("u", us), ("th", ts)],
                     [("f", f), ("Fx", Fx), ("Ft", Ft)], "double")
    kernels = unit.source()
    consts = [f"static const real_t DT = {float(dt)!r};"] + [
        c_array(k, v) for k, v in data.items()
        if k in ("S0", "R_NOISE", "CFG") or k in kernels or k in rhs]
    doubles = (stage1.sizes["state"] + N + N * N + r * r + cfg.size + 6 * p + 3 + max(m, 1)
               + 4 * p + n + (5 * m if est.hold == "smooth" else 0))
    refined = f"{stage1.name}_x_hat_refined(" in stage1.header     # Sec. VI's x̂₂
    sizes = {"n": n, "m": m, "r": r, "p": p, "hold": est.hold, "substeps": substeps,
             "x_stage1": "x_hat_refined" if refined else "x_hat",
             "state_doubles": doubles}
    banner = _banner(name, title, dt, substeps, est)
    source = guarded_source(name, banner, consts, rhs, kernels,
                            loop=f"{loop.name}({', '.join(loop.args)})",
                            init=f"{init.name}({', '.join(init.args)})",
                            fit=f"{fit.name}({', '.join(fit.args)})", samples=samples,
                            sizes=sizes)
    return GuardedCode(name=name, dt=float(dt), stage1=stage1,
                       header=guarded_header(name, banner, sizes), source=source,
                       main=guarded_main(name, banner, sizes),
                       makefile=guarded_makefile(name), sizes=sizes)


def _banner(name: str, title: str, dt: float, substeps: int, est: GuardedEstimator) -> str:
    lines = [f"{name}: the guarded estimator of thetahat (stage 1 the paper's observer, "
             "stage 2 the joint EKF on col(x, theta), the guard), one sample per call; no "
             "re-anchoring fits.", comment_text(title) if title else "",
             f"dt = {dt!r} s, stage 2 hold {est.hold}, RK4 sub-steps >= {substeps} (h*rho <= "
             f"{est.h_rho!r}), q_x = {est.q_x!r}; guard kappa = {est.kappa!r}, c = "
             f"{est.c!r}, rho_max = {est.rho_max!r}, dwell = {est.dwell!r}.",
             "Generated by thetahat codegen --method guarded; do not edit."]
    return "/*\n" + "".join(f" * {line}\n" for line in lines if line) + " */\n"

