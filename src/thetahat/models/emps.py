"""The EMPS benchmark: a real positioning system, its record, published table and validation.

The Electro-Mechanical Positioning System (Janot, Gautier & Brunot 2019) is a prismatic joint:
a DC motor drives a load through a ball screw. Its inverse dynamic model (the description's
eq. 1) is

    τ = M q̈ + Fv q̇ + Fc sign(q̇) + offset,

with the force τ = gτ ν from the controller output ν (eq. 7, gτ = 35.15 N/V). The joint runs in
closed loop under the PD law (eq. 6)

    ν = kp kv (q_r − q) − kv q̇_m,    kp = 160.18 1/s,  kv = 243.45 V/(m/s),

saturated at ±10 V, at 1 kHz, where q̇_m is the controller's velocity: the encoder position
through the FIR filter q_f(k) = (q(k) + q(k−1))/2, differenced, q̇_m(k) = (q_f(k) − q_f(k−1))/dt
(the description's section 2.2).

This module holds what belongs to the benchmark, not to an estimator: :func:`load` (the record
shipped in ``examples/data/emps/``), :data:`PUBLISHED` (the IDIM-LS table of the description's
section 3.4), :data:`PUBLISHED_VALIDATION` (its closed-loop figures, section 3.5) and
:func:`validate`, which simulates the closed loop with a given θ = (M, Fv, Fc, offset) and
returns the relative errors of eq. (11), ``100 ‖y − ŷ‖ / ‖y‖`` in %, of position, velocity and
force. ``examples/emps.toml`` is the estimation model of the same machine.

References
----------
A. Janot, M. Gautier and M. Brunot, "Data Set and Reference Models of EMPS", Workshop on
Nonlinear System Identification Benchmarks, 2019.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_vector
from ..errors import DimensionError, ModelFileError, ParameterSetError

__all__ = ["DATA_FILE", "EmpsRecord", "EmpsValidation", "G_TAU", "KP", "KV", "PUBLISHED",
           "PUBLISHED_VALIDATION", "PublishedTable", "SATURATION", "controller_velocity",
           "load", "relative_error", "simulate_closed_loop", "validate"]

FloatArray = NDArray[np.float64]

#: Proportional gain of the position loop (1/s), eq. (6).
KP = 160.18
#: Gain of the velocity loop (V/(m/s)), eq. (6).
KV = 243.45
#: Drive gain (N/V): τ = G_TAU · ν, eq. (7).
G_TAU = 35.15
#: Saturation of the controller output ν (V), the description's simulation settings.
SATURATION = 10.0
#: The record shipped with the repository (``examples/data/emps/DATA_EMPS.mat``).
DATA_FILE = Path(__file__).resolve().parents[3] / "examples" / "data" / "emps" / "DATA_EMPS.mat"


@dataclass(frozen=True, slots=True, repr=False)
class PublishedTable:
    """A published estimate: values and standard deviations per parameter.

    Attributes
    ----------
    names : tuple of str
    value, sigma : ndarray, shape (p,)
    source : str
    """

    names: tuple[str, ...]
    value: FloatArray
    sigma: FloatArray
    source: str

    def __repr__(self) -> str:
        rows = ", ".join(f"{n}={v:g}±{s:g}" for n, v, s in zip(self.names, self.value,
                                                              self.sigma))
        return f"PublishedTable({rows}; {self.source})"


def _frozen(values: ArrayLike) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.setflags(write=False)
    return arr


#: IDIM-LS estimate of θ = (M [kg], Fv [N s/m], Fc [N], offset [N]) on DATA_EMPS with its
#: standard deviations (the description's section 3.4).
PUBLISHED = PublishedTable(names=("M", "Fv", "Fc", "offset"),
                           value=_frozen([95.1089, 203.5034, 20.3935, -3.1648]),
                           sigma=_frozen([0.1085, 1.1460, 0.1012, 0.0444]),
                           source="Janot, Gautier & Brunot 2019, sec. 3.4 (IDIM-LS)")
#: Relative errors (eq. 11, %) of the closed loop simulated with :data:`PUBLISHED` on DATA_EMPS
#: (the description's section 3.5, as printed by its Simulink model).
PUBLISHED_VALIDATION = {"position": 0.013752, "velocity": 0.22911, "force": 5.848}


@dataclass(frozen=True, slots=True, repr=False)
class EmpsRecord:
    """The EMPS record in the estimation model's signals.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Time (s).
    u : ndarray, shape (N, 1)
        Force τ = G_TAU · vir (N).
    y : ndarray, shape (N, 1)
        Motor position q_m on the load side (m).
    q_ref : ndarray, shape (N,)
        The controller's reference position q_r (``qg``, m).
    """

    t: FloatArray
    u: FloatArray
    y: FloatArray
    q_ref: FloatArray

    def __repr__(self) -> str:
        return (f"EmpsRecord(N={self.t.size}, t=[{self.t[0]:g}, {self.t[-1]:g}] s, "
                f"fs={1.0 / float(np.median(np.diff(self.t))):.6g} Hz)")


def load(path: str | Path | None = None) -> EmpsRecord:
    """Read an EMPS record (``t``, ``qm``, ``vir``, ``qg`` of a benchmark MAT file).

    Parameters
    ----------
    path : str or Path, optional
        A MAT file with the variables of DATA_EMPS.mat (default: :data:`DATA_FILE`, the copy
        in the repository's ``examples/data/emps/``).

    Returns
    -------
    EmpsRecord
        t, u = τ = G_TAU · vir, y = qm and the reference q_r = qg.

    Raises
    ------
    ModelFileError
        The file is missing (e.g. an installed package without the repository's examples:
        pass the path), unreadable, or lacks one of the variables.

    Examples
    --------
    >>> from thetahat.models import emps
    >>> record = emps.load()
    >>> record.t.size, record.u.shape, record.y.shape
    (24841, (24841, 1), (24841, 1))
    """
    from ..io.matfile import read_mat_variables

    path = DATA_FILE if path is None else Path(path)
    if not path.is_file():
        raise ModelFileError(f"EMPS data file {path} not found; pass the path of "
                             f"DATA_EMPS.mat (in the repository: examples/data/emps/).")
    variables = read_mat_variables(path)
    missing = [v for v in ("t", "qm", "vir", "qg") if v not in variables]
    if missing:
        raise ModelFileError(f"EMPS data file {path} lacks the variable(s) {missing}; it has "
                             f"{sorted(variables)}.")
    t, qm, vir, qg = (np.asarray(variables[v], dtype=np.float64).ravel()
                      for v in ("t", "qm", "vir", "qg"))
    arrays = (t, (G_TAU * vir)[:, None], qm[:, None], qg)
    for arr in arrays:
        arr.setflags(write=False)
    return EmpsRecord(*arrays)


def relative_error(y: ArrayLike, y_hat: ArrayLike) -> float:
    """The benchmark's relative error, eq. (11): ``100 · ‖y − ŷ‖ / ‖y‖`` in %.

    Parameters
    ----------
    y : array_like, shape (N,)
        Measured.
    y_hat : array_like, shape (N,)
        Simulated or reconstructed.

    Returns
    -------
    float

    Examples
    --------
    >>> from thetahat.models.emps import relative_error
    >>> relative_error([3.0, 4.0], [3.0, 3.0])
    20.0
    """
    y, y_hat = np.asarray(y, dtype=np.float64), np.asarray(y_hat, dtype=np.float64)
    return float(100.0 * np.linalg.norm(y - y_hat) / np.linalg.norm(y))


def controller_velocity(q: ArrayLike, t: ArrayLike) -> FloatArray:
    """The controller's velocity: q filtered by (q(k) + q(k−1))/2, then differenced (sec. 2.2).

    q̇_m(k) = (q_f(k) − q_f(k−1)) / dt = (q(k) − q(k−2)) / (2 dt), with q(−1) = q(−2) = q(0):
    a central difference one sample late. The benchmark's "velocity" of eq. (11) is this
    signal, measured (from q_m) and simulated (from q_s) alike.

    Parameters
    ----------
    q : array_like, shape (N,)
        Positions (m).
    t : array_like, shape (N,)
        Sample times (s).

    Returns
    -------
    ndarray, shape (N,)

    Examples
    --------
    >>> from thetahat.models.emps import controller_velocity
    >>> controller_velocity([0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0]).tolist()
    [0.0, 0.5, 1.0, 1.0]
    """
    q, t = np.asarray(q, dtype=np.float64), np.asarray(t, dtype=np.float64)
    q_f = 0.5 * (q + np.concatenate([q[:1], q[:-1]]))
    out = np.zeros_like(q)
    out[1:] = np.diff(q_f) / np.diff(t)
    return out


def _slide(x1: float, x2: float, tau: float, h: float, theta: tuple[float, ...]
           ) -> tuple[float, float]:
    """The plant M q̈ + Fv q̇ + Fc sign(q̇) + offset = τ over h with τ held: exact.

    Between friction switches q̇ obeys a linear ODE, q̇(s) = v∞ + (q̇ − v∞) e^{−a s} with
    a = Fv/M; a zero crossing of q̇ is located in closed form, and at q̇ = 0 the load sticks
    while |τ − offset| ≤ Fc (sign(0) = 0, the force cannot overcome Coulomb friction).
    """
    M, Fv, Fc, offset = theta
    a = Fv / M
    left = h
    while left > 0.0:
        s = math.copysign(1.0, x2) if x2 != 0.0 else 0.0
        if s == 0.0:
            drive = tau - offset
            if abs(drive) <= Fc:
                return x1, 0.0                       # stuck for the rest of the interval
            s = math.copysign(1.0, drive)
        v_inf = (tau - Fc * s - offset) / Fv
        span = left
        if v_inf * s < 0.0 and x2 != 0.0:            # decelerates through q̇ = 0
            span = min(left, math.log((x2 - v_inf) / -v_inf) / a)
        decay = math.exp(-a * span)
        x1 += v_inf * span + (x2 - v_inf) * (1.0 - decay) / a
        x2 = v_inf + (x2 - v_inf) * decay
        left -= span
        if left > 0.0:
            x2 = 0.0
    return x1, x2


@dataclass(frozen=True, slots=True, repr=False)
class EmpsValidation:
    """The closed loop simulated with θ, compared with the record (eq. 11).

    Attributes
    ----------
    theta : ndarray, shape (4,)
        (M, Fv, Fc, offset) simulated.
    position, velocity, force : float
        Relative errors (%) of q_s vs q_m, of the controller velocities
        (:func:`controller_velocity`) and of the forces G_TAU · ν_s vs G_TAU · vir.
    q_sim, force_sim : ndarray, shape (N,)
        Simulated position (m) and force (N).
    """

    theta: FloatArray
    position: float
    velocity: float
    force: float
    q_sim: FloatArray
    force_sim: FloatArray

    def table(self) -> str:
        """The three errors beside the published IDIM-LS figures, as text.

        Returns
        -------
        str
        """
        lines = ["relative error (eq. 11)   this θ      published IDIM-LS"]
        for key in ("position", "velocity", "force"):
            lines.append(f"{key:<25} {getattr(self, key):9.4g} %  "
                         f"{PUBLISHED_VALIDATION[key]:9.4g} %")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"EmpsValidation(theta={self.theta.tolist()}, position={self.position:.4g} %, "
                f"velocity={self.velocity:.4g} %, force={self.force:.4g} %)")


def simulate_closed_loop(theta: ArrayLike, record: EmpsRecord, *,
                         disturbance: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
    """Simulate the EMPS under its PD controller (eqs. 3, 6, 7) along the record's reference.

    The controller runs at the record's samples: at t_k it reads q(t_k), forms ν_k by eq. (6)
    with :func:`controller_velocity`'s filtered difference, saturates it at ±SATURATION and
    holds τ = G_TAU · ν_k until t_{k+1}; the plant (eq. 3, sign friction with sticking at
    q̇ = 0) is integrated exactly over each interval. It starts at rest at q_m(0).

    Parameters
    ----------
    theta : array_like, shape (4,)
        (M, Fv, Fc, offset) with M > 0, Fv > 0, Fc ≥ 0.
    record : EmpsRecord
        The measured record (its t, q_ref and q_m(0) are used).
    disturbance : array_like, shape (N,), optional
        A force (N) acting on the load besides the motor's, held over each sample like τ:
        the benchmark's cross-test record applies force pulses this way. Default: none.

    Returns
    -------
    q_sim, nu_sim : ndarray, shape (N,)
        Simulated position (m) and controller output (V).

    Raises
    ------
    ParameterSetError
        M or Fv not positive, or Fc negative.
    DimensionError
        theta does not have 4 entries, or disturbance is not one number per sample.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import emps
    >>> rec = emps.load()
    >>> q, nu = emps.simulate_closed_loop(emps.PUBLISHED.value, rec)
    >>> bool(emps.relative_error(rec.y[:, 0], q) < 0.1)        # within 0.1 % of q_m (eq. 11)
    True
    """
    th = as_vector("theta", theta)
    if th.size != 4:
        raise DimensionError(f"theta: expected (M, Fv, Fc, offset), 4 numbers; got {th.size}.")
    M, Fv, Fc, offset = (float(v) for v in th)
    if not (M > 0 and Fv > 0 and Fc >= 0):
        raise ParameterSetError(f"theta = {th.tolist()}: the EMPS model needs M > 0, Fv > 0 "
                                f"and Fc >= 0.")
    t, q_ref = record.t, record.q_ref
    N = t.size
    push = np.zeros(N) if disturbance is None else as_vector("disturbance", disturbance)
    if push.size != N:
        raise DimensionError(f"disturbance: expected one force per sample ({N}); got "
                             f"{push.size}.")
    q_sim, nu_sim = np.empty(N), np.empty(N)
    x1, x2 = float(record.y[0, 0]), 0.0
    q_prev = q_f_prev = x1
    for k in range(N):
        q_sim[k] = x1
        q_f = 0.5 * (x1 + q_prev)
        velocity = (q_f - q_f_prev) / (t[k] - t[k - 1]) if k else 0.0
        nu = KP * KV * (q_ref[k] - x1) - KV * velocity
        nu_sim[k] = min(SATURATION, max(-SATURATION, nu))
        q_prev, q_f_prev = x1, q_f
        if k + 1 < N:
            x1, x2 = _slide(x1, x2, G_TAU * nu_sim[k] + push[k], t[k + 1] - t[k],
                            (M, Fv, Fc, offset))
    return q_sim, nu_sim


def validate(theta: ArrayLike, record: EmpsRecord | None = None) -> EmpsValidation:
    """The benchmark's validation: simulate the closed loop with θ, compare by eq. (11).

    Parameters
    ----------
    theta : array_like, shape (4,)
        (M, Fv, Fc, offset).
    record : EmpsRecord, optional
        Default: :func:`load` (DATA_EMPS).

    Returns
    -------
    EmpsValidation

    Raises
    ------
    ParameterSetError, DimensionError
        As for :func:`simulate_closed_loop`.

    Notes
    -----
    Position: ‖q_m − q_s‖/‖q_m‖; velocity: the same on :func:`controller_velocity` of both;
    force: on G_TAU · vir and G_TAU · ν_s. All in %, eq. (11) of the description.

    Examples
    --------
    >>> from thetahat.models import emps
    >>> check = emps.validate(emps.PUBLISHED.value)
    >>> round(check.force, 1)
    5.3
    """
    record = load() if record is None else record
    q_sim, nu_sim = simulate_closed_loop(theta, record)
    q_m, tau_m = record.y[:, 0], record.u[:, 0]
    force_sim = G_TAU * nu_sim
    for arr in (q_sim, force_sim):
        arr.setflags(write=False)
    return EmpsValidation(
        theta=_frozen(as_vector("theta", theta)),
        position=relative_error(q_m, q_sim),
        velocity=relative_error(controller_velocity(q_m, record.t),
                                controller_velocity(q_sim, record.t)),
        force=relative_error(tau_m, force_sim), q_sim=q_sim, force_sim=force_sim)
