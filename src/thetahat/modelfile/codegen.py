"""C for the estimator a model file describes: ``thetahat codegen``.

:func:`generate_c_from_model` reads a model file, builds the paper's observer it describes and
prints it as C with :func:`~thetahat.codegen.generate.generate_c` (the file's θ̂(0) and x̂(0)
as the defaults, the SHA-256 of its bytes in the header); :func:`generate_ekf_c_from_model`
prints the joint EKF on the file's model (``--method ekf``,
:func:`~thetahat.codegen.ekf_c.generate_ekf_c`) and :func:`generate_guarded_c_from_model`
both with the guard between them (``--method guarded``,
:func:`~thetahat.codegen.guarded_c.generate_guarded_c`). It lives here, above both the model
files and the code generator, so that :mod:`thetahat.codegen` never reads a model file.
"""

from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path
from typing import Any

from numpy.typing import ArrayLike

from ..codegen.c_text import name_from_stem, name_problem, suggest_name
from ..codegen.ekf_c import EKFCode, generate_ekf_c
from ..codegen.generate import CCode, generate_c
from ..codegen.guarded_c import GuardedCode, generate_guarded_c
from ..errors import OptionError, UnsupportedError
from ..estimation.statistical.common import resolve_noise_std
from ..estimation.records import check_record
from ..estimation.statistical.ekf import JointEKF
from ..estimation.statistical.guarded import GuardedEstimator
from ..estimation.statistical.input_hold import stage2_samples
from ..estimation.statistical.plant_kernel import choose_substeps
from .assembly import build_observer, resolve_gains
from .holds import split_hold
from .schema import ModelSpec, load_model

__all__ = ["generate_c_from_model", "generate_ekf_c_from_model", "generate_guarded_c_from_model"]


def _c_name(path: str | Path, name: str | None) -> str:
    if name is not None:
        return name
    name = name_from_stem(Path(path).stem)
    problem = name_problem(name)
    if problem is not None:
        raise OptionError(f"{path}: no C name was given and the one made from the file's "
                          f"name, {name!r}, cannot be used: {problem}; pass one with "
                          f"--name (name= in Python), e.g. {suggest_name(name)!r}.")
    return name


def generate_c_from_model(path: str | Path, *, dt: float, eps: float | None = None,
                          Gamma: ArrayLike | None = None, real: str = "double",
                          name: str | None = None, nan_policy: str = "raise",
                          hold: str = "zoh") -> CCode:
    """:func:`~thetahat.codegen.generate.generate_c` for the estimator of a model file (``thetahat codegen``).

    Parameters
    ----------
    path : str or Path
        Model file (.toml or .json).
    dt : float
        The fixed step length (s).
    eps : float, optional
        Overrides ``[estimator] eps``.
    Gamma : float or array_like, optional
        Γ of the update law in place of the file's: required when the file says
        ``Gamma = "auto"``, which is chosen on a record. Give the Γ ``thetahat estimate``
        printed, or choose it on the log with :func:`~thetahat.modelfile.resolve_gains`
        (``thetahat codegen --data LOG``), as the estimate does.
    real : {"double", "float"}
    name : str, optional
        File stem and C prefix (a C identifier the generated code can use:
        :func:`~thetahat.codegen.c_text.check_c_name`); default the model file's stem made
        one (:func:`~thetahat.codegen.c_text.name_from_stem`: ``two-mass.toml`` gives
        ``two_mass``).
    nan_policy : {"raise", "skip"}
        A NaN output sample is refused, or predicted over.
    hold : {"zoh", "foh"}
        Sample hold.

    Returns
    -------
    CCode
        With the file's θ̂(0) and x̂(0) as defaults and the SHA-256 of the file's bytes in the
        header.

    Raises
    ------
    ModelFileError
        The file cannot be read or is invalid, or it says ``Gamma = "auto"`` and no ``Gamma``
        is given.
    OptionError
        ``name`` (or the one made from the file's name) cannot name generated C: the message
        says why and names one that can.
    UnsupportedError
        A part of the estimator has no C form, or the file's ``[estimator] method`` names
        another method than ``"paper"`` (the guarded and MAP estimators have no C form; the
        file is refused, never generated as another method). A file that names no method
        (the default, guarded, for ``thetahat estimate``) generates the paper's observer:
        the one estimator with a C form.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "prop3.toml"
    >>> _ = path.write_text(EXAMPLE_MODEL)
    >>> generate_c_from_model(path, dt=0.01).name
    'prop3'
    """
    spec = load_model(path)
    if spec.estimator.method_given and spec.estimator.method != "paper":
        raise UnsupportedError(
            f"{path}: [estimator] method = {spec.estimator.method!r} has no C form; codegen "
            "generates the paper's estimator only (method = \"paper\"). Set method = "
            "\"paper\" in a copy of the file to generate the observer alone.")
    name = _c_name(path, name)
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    observer = build_observer(spec, eps=eps, Gamma=Gamma, nan_policy=nan_policy)
    return generate_c(observer.with_run_options(hold=hold), dt=dt, name=name,
                      real=real,
                      theta_hat0=spec.estimator.theta_hat0, x_hat0=spec.estimator.x_hat0,
                      eps=spec.estimator.eps if eps is None else eps, model_sha256=digest,
                      title=spec.name, x_hat0_from_y=spec.estimator.x_hat0_from_y)


def generate_ekf_c_from_model(path: str | Path, *, dt: float,
                              noise_std: ArrayLike | None = None,
                              record: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
                              name: str | None = None, hold: str = "zoh",
                              q_x: float = 0.0) -> EKFCode:
    """:func:`~thetahat.codegen.ekf_c.generate_ekf_c` for the model of a model file
    (``thetahat codegen --method ekf``).

    Parameters
    ----------
    path : str or Path
        Model file (.toml or .json); its [estimator] θ̂(0) and x̂(0) are the prior means.
    dt : float
        The sampling interval (s).
    noise_std : float or array_like (r,), optional
        σ of the output noise (R = σ² I).
    record : (t, u, y), optional
        A record (as :meth:`JointEKF.run <thetahat.estimation.statistical.ekf.JointEKF.run>`
        takes it) on which, as ``run`` does, σ is estimated when ``noise_std`` is not given
        and the RK4 sub-steps' floor is chosen
        (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`); without
        one the floor is 1, as :meth:`JointEKF.step` has it.
    name : str, optional
        File stem and C prefix (default: the file's stem made a C identifier).
    hold : str
        ``"zoh"``, ``"foh"`` or ``"smooth"`` (the holds the C EKF has,
        :data:`~thetahat.codegen.ekf_c.C_HOLDS`).
    q_x : float
        Process-noise variance per sample on x.

    Returns
    -------
    EKFCode

    Raises
    ------
    ModelFileError
        The file cannot be read or is invalid.
    OptionError
        Neither ``noise_std`` nor ``record``, or a name that cannot be used.
    UnsupportedError
        What the C EKF cannot do (:mod:`thetahat.codegen.ekf_c`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "prop3.toml"
    >>> _ = path.write_text(EXAMPLE_MODEL)
    >>> generate_ekf_c_from_model(path, dt=0.01, noise_std=0.01).name
    'prop3'
    """
    spec = load_model(path)
    name = _c_name(path, name)
    ekf = JointEKF(system=spec.system, noise_std=noise_std, hold=hold, q_x=q_x, compiled=False)
    ekf = replace(ekf, **_stage2_options(spec, path, ekf, noise_std, record, "the C EKF"))
    return generate_ekf_c(ekf, dt=dt, name=name, x_hat0=spec.estimator.x_hat0,
                          theta_hat0=spec.estimator.theta_hat0, title=spec.name)


def _stage2_options(spec: ModelSpec, path: str | Path, ekf: JointEKF,
                    noise_std: ArrayLike | None,
                    record: tuple[ArrayLike, ArrayLike, ArrayLike] | None,
                    what: str) -> dict[str, Any]:
    """Stage 2's σ and sub-step floor for generated C: σ given or estimated on the record
    and the floor chosen there (as ``run`` does), else σ given and the floor 1 (as ``step``)."""
    if record is not None:
        t, U, Y = check_record(*record, m=spec.system.m, r=spec.system.r)
        sigma = resolve_noise_std(noise_std, Y)
        Ut = stage2_samples(U, ekf.hold)[0]
        est = spec.estimator
        substeps = choose_substeps(ekf.kernels.model, t, Ut, Y, est.theta_hat0, est.x_hat0,
                                   sigma, hold=ekf.hold, h_rho=ekf.h_rho)
        return {"noise_std": sigma, "substeps": substeps}
    if noise_std is None:
        raise OptionError(f"{path}: {what} needs the output noise σ: give it "
                          "(--noise-std), or a record to estimate it from (--data LOG).")
    return {}


def generate_guarded_c_from_model(path: str | Path, *, dt: float, eps: float | None = None,
                                  Gamma: ArrayLike | None = None,
                                  noise_std: ArrayLike | None = None,
                                  record: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
                                  name: str | None = None, hold: str = "zoh",
                                  q_x: float = 0.0) -> GuardedCode:
    """:func:`~thetahat.codegen.guarded_c.generate_guarded_c` for the model of a model file
    (``thetahat codegen --method guarded``): stage 1 the file's observer (as
    :func:`generate_c_from_model`), stage 2 the joint EKF (as
    :func:`generate_ekf_c_from_model`), the guard; no re-anchoring fits.

    Parameters
    ----------
    path : str or Path
        Model file (.toml or .json); its [estimator] θ̂(0) and x̂(0) are both stages' start.
    dt : float
        The sampling interval (s).
    eps, Gamma : optional
        Stage 1's ε and Γ in place of the file's (``Gamma = "auto"`` needs ``Gamma`` or a
        ``record`` to choose it on, as :func:`~thetahat.modelfile.resolve_gains`).
    noise_std : float or array_like (r,), optional
        σ of the output noise; default estimated on ``record``.
    record : (t, u, y), optional
        A record: Γ ``"auto"`` is chosen, σ estimated and stage 2's RK4 sub-step floor
        chosen on it; without one the floor is 1 (as :meth:`GuardedEstimator.step
        <thetahat.estimation.statistical.guarded.GuardedEstimator.step>`).
    name : str, optional
        File stem and C prefix (default: the file's stem made a C identifier).
    hold : str
        ``"zoh"``, ``"foh"`` or ``"smooth"``: stage 2's, and the hold Γ ``"auto"`` is chosen
        under (``"foh"`` for ``"smooth"``; stage 1 steps with the samples held, as
        :meth:`GuardedEstimator.step
        <thetahat.estimation.statistical.guarded.GuardedEstimator.step>` has it).
    q_x : float
        Stage 2's process-noise variance per sample on x.

    Returns
    -------
    GuardedCode

    Raises
    ------
    ModelFileError
        The file cannot be read or is invalid, or Γ is ``"auto"`` with neither ``Gamma``
        nor ``record``.
    OptionError
        Neither ``noise_std`` nor ``record``, or a name that cannot be used.
    UnsupportedError
        What the guarded C cannot do (:mod:`thetahat.codegen.guarded_c`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "prop3.toml"
    >>> _ = path.write_text(EXAMPLE_MODEL)
    >>> sorted(generate_guarded_c_from_model(path, dt=0.01, noise_std=0.01).files())[:3]
    ['Makefile', 'prop3.c', 'prop3.h']
    """
    spec = load_model(path)
    name = _c_name(path, name)
    rec = () if record is None else tuple(record)
    gains = resolve_gains(spec, *rec, eps=eps, Gamma=Gamma, hold=hold)
    observer = build_observer(spec, eps=gains.eps, Gamma=gains.Gamma).with_run_options(
        hold=split_hold(hold, "guarded")[0])          # "smooth" is stage 2's: stage 1 "foh"
    ekf = JointEKF(system=spec.system, noise_std=noise_std, hold=hold, q_x=q_x, compiled=False)
    options = _stage2_options(spec, path, ekf, noise_std, record, "the guarded C")
    est = GuardedEstimator(stage1=observer, system=spec.system,
                           noise_std=options.get("noise_std", noise_std), hold=hold,
                           q_x=q_x, use_fits=False, substeps=options.get("substeps"),
                           compiled=False)
    return generate_guarded_c(est, dt=dt, name=name, x_hat0=spec.estimator.x_hat0,
                              theta_hat0=spec.estimator.theta_hat0, eps=gains.eps,
                              title=spec.name)
