"""The ``thetahat`` command line: a thin argparse layer over the public API.

Subcommands::

    thetahat demo lugre [--out out] [--eps 1] [--seed 0] [--show]
    thetahat demo emps [--out out]
    thetahat demo silverbox [--out out]
    thetahat sweep [MODEL] [--eps 1 0.7 0.5 0.3 0.2 0.1] [--seeds 5] [--t-end T] [--out out]
                   [--jobs N] [--scheduler tcp://HOST:PORT]
    thetahat tune [MODEL] [--eps 1 0.7 0.5 0.3] [--gamma 1 3 10 30] [--seeds 1000 1001]
                  [--t-end T] [--out out] [--jobs N] [--scheduler tcp://HOST:PORT]
    thetahat analyze MODEL
    thetahat estimate MODEL DATA.csv [-o estimates.csv] [--hold zoh|foh|bandlimited] [--nan-policy raise|skip]
                      [--no-progress | --quiet] [--method M] [--plot fig.png]
                      [--noise-std SIGMA] [--samples NAME|START:STOP|all] [--summary RUN.json]
    thetahat estimate MODEL logs/ [-o results.csv|.parquet] [--scheduler tcp://HOST:PORT]
                      [--method M] [--nan-policy raise|skip]
    thetahat codegen MODEL --dt 1e-3 [--eps 1] [--gamma G... | --data LOG]
                     [--real double|float] [--name NAME] [--nan-policy raise|skip]
                     [--hold zoh|foh] -o DIR
    thetahat codegen MODEL --method ekf --dt 1e-3 (--noise-std S | --data LOG)
                     [--hold zoh|foh|smooth] -o DIR
    thetahat codegen MODEL --method guarded --dt 1e-3 (--noise-std S | --data LOG)
                     [--hold zoh|foh|smooth] -o DIR

Exit codes (see ``EXIT_CODES``): 0 success; 1 the model fails the theory's checks (Assumption 1
fails, or the design is unstable on the true system); 2 usage or input error (the message is
printed as ``thetahat: error: ...``, without a traceback; ``--debug`` shows it); 3 internal
error (a bug: please report it with the ``--debug`` traceback); 130 interrupted; 141 the
reader of the output went away (``thetahat … | head``): quietly, as the shell reports coreutils
killed by SIGPIPE (128 + 13).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

# The command's own process: one BLAS thread unless the user asks for more (before NumPy loads
# OpenBLAS). thetahat's matrices are small (n ≲ 10, p ≲ 10); BLAS threads spinning on busy
# cores made a 4×4 expm 500× slower and the EMPS MAP fits 7.6 → 5.2 s of CPU (one run, loaded).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ._version import __version__  # noqa: E402
from .errors import (NotLeftInvertibleError, NotMinimumPhaseError, OptionError, ThetahatError,
                     UnstableDesignError)

if TYPE_CHECKING:
    from .estimation.protocol import EstimateResult
    from .io.record import DataRecord
    from .modelfile.assembly import ObserverGains
    from .progress import Stages

EXIT_OK = 0
EXIT_CHECK = 1
EXIT_INPUT = 2
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130
#: The reader of the output closed the pipe (``thetahat estimate … | head``). coreutils leave
#: SIGPIPE at its default and die of it, which the shell reports as 128 + 13 = 141 (and
#: ``set -o pipefail`` as the pipeline's failure); Python ignores SIGPIPE (a write raises
#: BrokenPipeError instead), so the command returns 141 itself, without a message or a
#: traceback. Not 0: output was lost, and a step after the print (a sweep's JSON) did not run.
#: SIGPIPE is not restored instead: it would also kill the process on a socket or a worker's
#: pipe that closes (Dask, the guarded estimator's fit worker).
EXIT_PIPE = 141

#: The exit codes, as printed by ``thetahat --help``.
EXIT_CODES = ("Exit codes: 0 success (analyze: Assumption 1 holds and the design is stable on "
              "the true system); 1 the model fails these checks (Assumption 1 fails, or the "
              "design is unstable on the true system); 2 usage or input error (bad file, bad "
              "option; the message says what to fix, --debug shows the traceback); 3 internal "
              "error (please report it with the --debug output); 130 interrupted; 141 the "
              "output's reader went away (thetahat ... | head), as for coreutils.")

#: Errors that mean "the model violates the theory", exit code 1.
_CHECK_ERRORS = (NotMinimumPhaseError, NotLeftInvertibleError, UnstableDesignError)

#: Figure formats of ``--plot`` (Matplotlib's Agg backend).
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".eps", ".ps", ".tif",
                 ".tiff", ".webp", ".pgf")


def _inputs(*paths: str | None) -> list[str]:
    return [p for p in paths if p is not None]


def _check_plot(path: str, inputs: list[str]) -> None:
    """A figure path: its suffix, its folder and matplotlib, before any work."""
    import importlib.util

    from .errors import MissingExtraError
    from .safe_io import check_writable

    check_writable(path, inputs=inputs, suffixes=PLOT_SUFFIXES, what="figure")
    if importlib.util.find_spec("matplotlib") is None:
        raise MissingExtraError("--plot needs matplotlib: pip install 'thetahat[plot]', or "
                                "drop --plot.")


def _demo(args: argparse.Namespace) -> int:
    if args.example == "emps":
        from .models.emps_report import report as emps_report
        emps_report(out=args.out)
    elif args.example == "silverbox":
        from .models.silverbox_report import report as silverbox_report
        silverbox_report(out=args.out)
    else:
        from .models.lugre_report import report
        report(out=args.out, eps=args.eps, seed=args.seed, show=args.show)
    return EXIT_OK


def _study(args: argparse.Namespace) -> Any:
    """The :class:`~thetahat.modelfile.study.StudySetup` of MODEL, or of the LuGre example."""
    if args.model is None:
        from .models import lugre
        return lugre.study_setup(t_end=args.t_end)
    from .modelfile import load_model
    from .modelfile.study import study_setup

    setup = study_setup(load_model(args.model), t_end=args.t_end)
    if setup.assumed:           # the experiment itself was not given: say what was assumed
        print(f"thetahat: note: {setup.assumed}", file=sys.stderr)
    return setup


def _sweep(args: argparse.Namespace) -> int:
    from .safe_io import atomic_path, check_writable, write_text
    from .studies.sweep import eps_sweep

    out = Path(args.out)
    for name in ("sweep.json", "sweep.png"):                          # before any work
        check_writable(out / name, inputs=_inputs(args.model))
    setup = _study(args)
    result = eps_sweep(setup.estimator, setup.simulate, args.eps, range(args.seeds),
                       theta_hat0=setup.theta_hat0, n_jobs=args.jobs, scheduler=args.scheduler)
    print(result.table(setup.state_names))
    write_text(out / "sweep.json", json.dumps(result.to_dict(), indent=2))
    written = [out / "sweep.json"]
    try:
        from .plotting import plot_sweep
        with atomic_path(out / "sweep.png") as tmp:
            plot_sweep(result, tmp, state_labels=setup.state_names)
        written.append(out / "sweep.png")
    except ImportError as exc:
        print(f"thetahat: note: {exc}; sweep.png not written", file=sys.stderr)
    print("wrote " + " and ".join(str(p) for p in written))
    return EXIT_OK


def _tune(args: argparse.Namespace) -> int:
    from .safe_io import check_writable, write_text
    from .studies.tune import tune_eps_gamma

    check_writable(Path(args.out) / "tune.json", inputs=_inputs(args.model))   # before work
    setup = _study(args)
    result = tune_eps_gamma(setup.estimator, setup.simulate, eps_values=args.eps,
                            gammas=args.gamma, seeds=args.seeds, theta_hat0=setup.theta_hat0,
                            criterion=args.criterion, n_jobs=args.jobs,
                            scheduler=args.scheduler)
    print(result.table(setup.state_names))
    out = Path(args.out)
    write_text(out / "tune.json", json.dumps(result.to_dict(), indent=2))
    print(f"wrote {out / 'tune.json'}")
    if result.best_eps is None:
        print(f"thetahat: error: {result.verdict()}", file=sys.stderr)
        return EXIT_INPUT
    return EXIT_OK


def _analyze(args: argparse.Namespace) -> int:
    from .modelfile import analyze_model, load_model

    report = analyze_model(load_model(args.model))
    print(report)
    if not report.ok:
        print(f"thetahat: check failed: {report.verdict()}", file=sys.stderr)
        return EXIT_CHECK
    return EXIT_OK


def _is_fleet(data: str) -> bool:
    if Path(data).is_file():        # one record: no need to import the fleet's machinery
        return False
    from .fleet import is_glob

    return Path(data).is_dir() or is_glob(data)


def _check_estimate_outputs(args: argparse.Namespace) -> None:
    """-o and --plot, before any work."""
    from .io.datafile import ESTIMATE_SUFFIXES
    from .safe_io import check_writable, same_file

    inputs = [args.model, args.data]
    check_writable(args.output, inputs=inputs, suffixes=ESTIMATE_SUFFIXES, what="estimates")
    if args.plot:
        if same_file(args.plot, args.output):
            raise OptionError(f"--plot {args.plot} is also the estimates output (-o); give "
                              f"the figure its own name.")
        _check_plot(args.plot, inputs)
    if args.summary:           # .json: never the estimates (.csv/.parquet) or the figure
        check_writable(args.summary, inputs=inputs, suffixes=(".json",), what="summary")


#: The stages of ``thetahat estimate`` on one record, as its progress names them.
ESTIMATE_STAGES = ("load model", "read", "estimate", "trust report", "write")


def _with_fits(plan: tuple[str, ...]) -> tuple[str, ...]:
    """``plan`` with the stage "fits" after "estimate" (the methods that fit)."""
    at = plan.index("estimate") + 1
    return plan[:at] + ("fits",) + plan[at:]


def _progress_mode(args: argparse.Namespace) -> str:
    """--quiet: nothing; --no-progress: the final line only; else live on a terminal."""
    return "quiet" if args.quiet else "final" if args.no_progress else "auto"


def _estimate(args: argparse.Namespace) -> int:
    if _is_fleet(args.data):
        return _estimate_fleet(args)
    from .progress import Stages

    plan = ESTIMATE_STAGES + (("plot",) if args.plot else ())
    with Stages(plan, mode=_progress_mode(args)) as stages:     # first line before the imports
        stages.stage("load model")
        result, data, caught, gains = _estimate_one(args, stages)
    print(f"wrote {args.output} ({data.t.size} rows)")
    if gains is not None:                  # the Γ of "auto", for codegen --gamma
        print(gains)
    from .studies.metrics import estimate_summary
    print(estimate_summary(result, warnings=caught))
    if args.plot:
        print(f"wrote {args.plot}")
    if args.summary:
        _write_summary(args, result, caught, gains)
        print(f"wrote {args.summary}")
    return EXIT_OK


def _window(text: str | None) -> int | str | None:
    """``--window``: None, "auto" or a whole number of samples (parsed, never evaluated)."""
    if text is None or text == "auto":
        return text
    if not text.isdigit():
        raise OptionError(f"--window takes 'auto' or a whole number of samples; got {text!r}.")
    return int(text)


def _write_summary(args: argparse.Namespace, result: EstimateResult,
                   caught: list[warnings.WarningMessage], gains: ObserverGains | None) -> None:
    """--summary: the printed summary as JSON, with what the run resolved (ε, Γ)."""
    import numpy as np

    from .safe_io import write_text
    from .studies.metrics import estimate_record

    context: dict[str, object] = {
        "thetahat": __version__, "model": str(args.model), "data": str(args.data),
        "output": str(args.output), "method": args.method, "hold": args.hold,
        "samples_option": args.samples}
    if gains is not None:                      # what `thetahat codegen --eps/--gamma` takes
        context.update(eps=float(gains.eps), Gamma=np.asarray(gains.Gamma).tolist(),
                       gains_source=gains.source, eps_source=gains.eps_source)
    record = estimate_record(result, warnings=caught, context=context)
    write_text(args.summary, json.dumps(record, indent=2, ensure_ascii=False) + "\n")


def _estimate_one(args: argparse.Namespace, stages: Stages
                  ) -> tuple[EstimateResult, DataRecord, list[warnings.WarningMessage],
                             ObserverGains | None]:
    """The stages of one record: load, read, estimate (with the trust report), write, plot."""
    from .io.datafile import read_data, write_estimates
    from .methods import get_method
    from .modelfile import load_model, resolve_gains, run_estimator, split_hold
    from .safe_io import atomic_path

    args.output = args.output or "estimates.csv"
    _check_estimate_outputs(args)
    spec = load_model(args.model)
    how = get_method(args.method or spec.estimator.method)
    args.method = how.name                  # resolved once: the run and --summary name it
    split_hold(args.hold, how.name)         # a hold the method cannot take: refused first
    if how.fits:                        # run_estimator counts them in a stage of their own
        stages.plan = _with_fits(stages.plan)
    stages.stage("read")
    data = read_data(args.data, spec.layout, nan_policy=args.nan_policy,
                     delimiter=_delimiter(args.delimiter), samples=args.samples)
    stages.note(f"{data.t.size:,} rows" + ("" if data.samples is None else
                                          f" (samples [{data.samples[0]}, {data.samples[1]}))"))
    stages.stage("estimate", total=data.t.size)
    with warnings.catch_warnings(record=True) as caught:       # shown in the summary
        warnings.simplefilter("always")
        gains = (resolve_gains(spec, data.t, data.u, data.y, hold=args.hold,
                               nan_policy=args.nan_policy)
                 if how.runs_observer else None)
        result = run_estimator(spec, data.t, data.u, data.y, hold=args.hold,   # names the
                               nan_policy=args.nan_policy, progress=stages,    # trust report
                               method=args.method,
                               Gamma=None if gains is None else gains.Gamma,
                               eps=None if gains is None else gains.eps,
                               noise_std=args.noise_std, window=_window(args.window))
    stages.stage("write")
    stages.note(f"{data.t.size:,} rows to {args.output}")
    write_estimates(args.output, result, spec.layout)                         # atomic
    if args.plot:
        from .plotting import plot_result
        stages.stage("plot")
        with atomic_path(args.plot) as tmp:
            plot_result(result, spec, tmp, y=data.y)
    return result, data, caught, gains


def _estimate_fleet(args: argparse.Namespace) -> int:
    from .fleet import check_output, estimate_many, fleet_files

    output = args.output or "results.csv"
    if args.plot:
        raise OptionError("--plot draws one record; it is not available for a fleet (drop "
                          "--plot, or estimate one file).")
    if args.summary:
        raise OptionError("--summary describes one record; a fleet's results file (-o) "
                          "already holds one row per record.")
    if args.samples is not None:
        raise OptionError("--samples chooses samples of one record; for a fleet, give the "
                          "model file's [data] samples (it applies to every record).")
    check_output(output, args.model, fleet_files(args.data), args.data)   # before any work
    result = estimate_many(args.model, args.data, scheduler=args.scheduler,
                           chunk_size=args.chunk_size, hold=args.hold, method=args.method,
                           nan_policy=args.nan_policy,
                           progress=not (args.no_progress or args.quiet),
                           delimiter=_delimiter(args.delimiter), noise_std=args.noise_std,
                           window=_window(args.window))
    result.write(output)
    print(f"wrote {output} ({len(result.rows)} files: {result.n_ok} ok, "
          f"{len(result.rows) - result.n_ok} failed)")
    for file, reason in result.failed.items():
        print(f"thetahat: {file}: {reason}", file=sys.stderr)
    return EXIT_OK


def _codegen(args: argparse.Namespace) -> int:
    from .modelfile import generate_c_from_model, load_model, resolve_gains
    from .safe_io import check_writable

    inputs = _inputs(args.model, args.data)
    check_writable(Path(args.output) / "Makefile", inputs=inputs)         # before any work
    if args.method == "ekf":
        return _codegen_ekf(args, inputs)
    if args.method == "guarded":
        return _codegen_guarded(args, inputs)
    if args.noise_std is not None:
        raise OptionError("--noise-std is the EKF's σ: give it with --method ekf.")
    if args.hold == "smooth":
        raise OptionError("--hold smooth is stage 2's (--method ekf or guarded); the paper's "
                          "observer takes zoh or foh.")
    if args.data is not None and args.gamma is not None:
        raise OptionError("--gamma gives Γ and --data chooses it on a log: give one of them.")
    spec = load_model(args.model)
    record: tuple[Any, ...] = ()
    if args.data is not None:
        from .io.datafile import read_data
        data = read_data(args.data, spec.layout, nan_policy=args.nan_policy,
                         delimiter=_delimiter(args.delimiter))
        record = (data.t, data.u, data.y)
    gains = resolve_gains(spec, *record, eps=args.eps, Gamma=args.gamma, hold=args.hold,
                          nan_policy=args.nan_policy)
    code = generate_c_from_model(args.model, dt=args.dt, eps=gains.eps, Gamma=gains.Gamma,
                                 real=args.real, name=args.name, nan_policy=args.nan_policy,
                                 hold=args.hold)
    for name in code.files():
        check_writable(Path(args.output) / name, inputs=inputs)
    paths = code.write(args.output)
    print(code.summary())
    print(gains)
    print("wrote " + ", ".join(str(p) for p in paths)
          + f"; build the harness with: make -C {args.output}")
    return EXIT_OK


def _codegen_ekf(args: argparse.Namespace, inputs: list[str]) -> int:
    from .modelfile import generate_ekf_c_from_model

    given = [flag for flag, value in (("--eps", args.eps), ("--gamma", args.gamma))
             if value is not None] + (["--real float"] if args.real == "float" else [])
    if given:
        raise OptionError(f"{', '.join(given)} belong to the paper's observer; --method ekf "
                          "takes --noise-std (or --data), --hold and --name.")
    code = generate_ekf_c_from_model(args.model, dt=args.dt, noise_std=args.noise_std,
                                     record=_codegen_record(args), name=args.name,
                                     hold=args.hold)
    return _write_codegen(args, code, inputs)


def _codegen_guarded(args: argparse.Namespace, inputs: list[str]) -> int:
    from .modelfile import generate_guarded_c_from_model

    if args.real == "float":
        raise OptionError("--method guarded is generated in double only (stage 2's "
                          "covariance): drop --real float.")
    if args.data is not None and args.gamma is not None:
        raise OptionError("--gamma gives Γ and --data chooses it on a log: give one of them.")
    code = generate_guarded_c_from_model(args.model, dt=args.dt, eps=args.eps,
                                         Gamma=args.gamma, noise_std=args.noise_std,
                                         record=_codegen_record(args), name=args.name,
                                         hold=args.hold)
    return _write_codegen(args, code, inputs)


def _codegen_record(args: argparse.Namespace) -> tuple[Any, ...] | None:
    """--data's (t, u, y) in the model file's layout, or None."""
    if args.data is None:
        return None
    from .io.datafile import read_data
    from .modelfile import load_model
    data = read_data(args.data, load_model(args.model).layout, nan_policy=args.nan_policy,
                     delimiter=_delimiter(args.delimiter))
    return (data.t, data.u, data.y)


def _write_codegen(args: argparse.Namespace, code: Any, inputs: list[str]) -> int:
    """Write a generated set of files (none over an input) and say what was written."""
    from .safe_io import check_writable
    for name in code.files():
        check_writable(Path(args.output) / name, inputs=inputs)
    paths = code.write(args.output)
    print(code.summary())
    print("wrote " + ", ".join(str(p) for p in paths)
          + f"; build the harness with: make -C {args.output}")
    return EXIT_OK


# ---------------------------------------------------------------------------------------------
# The parser: one function per subcommand
# ---------------------------------------------------------------------------------------------

_Subparsers = Any      # argparse._SubParsersAction, private in argparse


def _add_demo(sub: _Subparsers) -> None:
    demo = sub.add_parser("demo", help="run the paper's example end to end (Sec. VIII)",
                          description="Run an example: structure, design, estimation, the "
                                      "figure (out/lugre.png), a summary (out/lugre.json) and "
                                      "the data (out/lugre_data.csv: t,u,y).")
    demo.add_argument("example", choices=["lugre", "emps", "silverbox"],
                      help="the example to run (emps: the measured EMPS benchmark; "
                           "silverbox: the measured Silverbox benchmark)")
    demo.add_argument("--out", default="out", help="output folder (default: out)")
    demo.add_argument("--eps", type=float, default=1.0, help="ε of the first observer "
                                                             "(default: 1)")
    demo.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    demo.add_argument("--show", action="store_true", help="open the figure window")
    demo.set_defaults(run=_demo)


def _add_study_options(parser: argparse.ArgumentParser, runs: str) -> None:
    """The options sweep and tune share: MODEL, --t-end, --jobs, --scheduler, --out."""
    parser.add_argument("model", nargs="?", default=None,
                        help="model file (.toml or .json); default: the LuGre example")
    parser.add_argument("--t-end", type=float, default=None,
                        help="simulated time in s (default: the scenario's; LuGre: 20)")
    parser.add_argument("--jobs", type=int, default=1,
                        help=f"worker processes{' over the ε values' if runs == 'ε' else ''} "
                             f"(default: 1; -1: all cores)")
    parser.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                        help=f"run the {runs} on this Dask cluster")
    parser.add_argument("--out", default="out", help="output folder (default: out)")


def _add_sweep(sub: _Subparsers) -> None:
    sweep = sub.add_parser("sweep", help="ε sweep of a model file or the LuGre example "
                                         "(Sec. VII)",
                           description="Run the estimator of MODEL (default: the LuGre "
                                       "example) for decreasing ε over several noise seeds, on "
                                       "records simulated from the file's [scenario]; print "
                                       "the table and where it stops being stable; write "
                                       "out/sweep.json and out/sweep.png.")
    sweep.add_argument("--eps", type=float, nargs="+", default=[1, 0.7, 0.5, 0.3, 0.2, 0.1],
                       help="ε values, starting at 1 and decreasing (default: 1 0.7 0.5 0.3 "
                            "0.2 0.1)")
    sweep.add_argument("--seeds", type=int, default=5,
                       help="number of noise seeds 0, 1, ... (default: 5)")
    _add_study_options(sweep, "ε × seeds runs")
    sweep.set_defaults(run=_sweep)


def _add_tune(sub: _Subparsers) -> None:
    tune = sub.add_parser("tune", help="pick ε and Γ for a model file or the LuGre example "
                                       "(Sec. VII)",
                          description="Grid search over (ε, Γ) on tuning seeds, ε decreasing "
                                      "from 1 (Sec. VII), for the estimator of MODEL (default: "
                                      "the LuGre example) on records simulated from its "
                                      "[scenario]: reject pairs that diverge, pick the "
                                      "smallest worst-case score; print the table and write "
                                      "out/tune.json.")
    tune.add_argument("--eps", type=float, nargs="+", default=[1, 0.7, 0.5, 0.3],
                      help="ε values, starting at 1 and decreasing (default: 1 0.7 0.5 0.3)")
    tune.add_argument("--gamma", type=float, nargs="+", default=[1, 3, 10, 30],
                      help="Γ values of the update law, > 0 and increasing (default: 1 3 10 "
                           "30)")
    tune.add_argument("--seeds", type=int, nargs="+", default=[1000, 1001],
                      help="tuning noise seeds (default: 1000 1001)")
    tune.add_argument("--criterion", choices=["theta_rmse", "t_1pct"], default="theta_rmse",
                      help="score to minimise, worst over the seeds (default: theta_rmse)")
    _add_study_options(tune, "ε")
    tune.set_defaults(run=_tune)


def _add_analyze(sub: _Subparsers) -> None:
    analyze = sub.add_parser("analyze", help="structural report of a model file",
                             description="Assumption 1, the SCB of the error system (4) (and "
                                         "of the design system), K(ε) and the closed-loop "
                                         "spectra on the design and true systems.",
                             epilog="Exit codes: 0 when Assumption 1 holds and the design is "
                                    "stable on the true system; 1 when not (the report says "
                                    "why); 2 for bad input (an unreadable or invalid file).")
    analyze.add_argument("model", help="model file (.toml or .json)")
    analyze.set_defaults(run=_analyze)


def _estimate_positionals(args: argparse.Namespace, usage_error: Any) -> None:
    """MODEL, then DATA: a usage error that says which is which when one is missing or the two
    are swapped (``usage_error`` is the subparser's ``error``, which exits 2)."""
    from .io.datafile import DATA_SUFFIXES

    def is_data(path: str) -> bool:
        return Path(path).suffix.lower() in DATA_SUFFIXES or _is_fleet(path)

    def is_model(path: str) -> bool:
        return Path(path).suffix.lower() in (".toml", ".json")

    if args.model is None:
        usage_error("give the model file (.toml or .json), then the record (a CSV, Parquet, "
                    "MATLAB or Excel file, or a directory of them): MODEL DATA.")
    elif args.data is None and is_data(args.model):
        usage_error(f"give the model file first (MODEL DATA): {args.model} looks like the "
                    f"record, e.g. thetahat estimate model.toml {args.model}")
    elif args.data is None:
        usage_error(f"DATA is missing (MODEL DATA): after the model file {args.model}, give the "
                    f"record to estimate from (a CSV, Parquet, MATLAB or Excel file, or a "
                    f"directory of them).")
    elif is_data(args.model) and is_model(args.data):
        usage_error(f"the model file comes first (MODEL DATA): thetahat estimate {args.data} "
                    f"{args.model}")


def _delimiter(choice: str | None) -> str | None:
    """The --delimiter choice as the reader takes it ("tab" is a tab character)."""
    return "\t" if choice == "tab" else choice


def _add_estimate(sub: _Subparsers) -> None:
    from .methods import ESTIMATION_METHODS, method_help

    estimate = sub.add_parser(
        "estimate", help="run a model file's estimator on a record or a fleet of records",
        usage="%(prog)s MODEL DATA [options]",
        description="Run the estimator of MODEL on DATA (CSV with a header: a column t, one "
                    "column per input named as in the model or u1, u2, ... (u when there is "
                    "one), one per output named as in the model or y1, ... (y when there is "
                    "one)). Writes t, x_hat_*, phi_hat_*, theta_hat_* and x_hat_refined_* "
                    "as CSV. With a directory or glob of CSV/Parquet files (a fleet): one row "
                    "per file with its status, the final theta_hat_*, their standard error, "
                    "settling time and warnings; a bad file is reported and never stops the "
                    "others.")
    # Both optional for argparse, checked after parsing (_estimate_positionals): its own
    # "required: data" does not say that a lone data file means the model file was forgotten.
    estimate.add_argument("model", metavar="MODEL", nargs="?", default=None,
                          help="model file (.toml or .json): first")
    estimate.add_argument("data", metavar="DATA", nargs="?", default=None,
                          help="the record: a CSV, Parquet, MATLAB (.mat) or Excel file, e.g. "
                               "with columns t,u,y; or a fleet: a directory or glob of them "
                               "(quote it)")
    estimate.add_argument("-o", "--output", default=None,
                          help="output, .csv or .parquet (default: estimates.csv; for a fleet "
                               "results.csv: one row per file); never one of the inputs")
    estimate.add_argument("--hold", choices=["zoh", "foh", "smooth", "bandlimited"],
                          default=None,
                          help="u between the samples, for every method: zoh (held by a "
                               "DAC), foh (linear between the samples), smooth (a smooth "
                               "signal sampled: linear through samples corrected for its "
                               "curvature) or bandlimited (the band-limited signal through "
                               "the samples; not the paper's method). Default: the observer "
                               "holds, the statistical methods take smooth")
    estimate.add_argument("--window", metavar="auto|W", default=None,
                          help="guarded and mle: bounded fits, each past W samples over the "
                               "samples since the previous one (auto: W from the record's "
                               "information); default: fits of all the data so far")
    estimate.add_argument("--nan-policy", choices=["raise", "skip"], default="raise",
                          help="empty or NaN output cells (dropouts): refuse the file (raise, "
                               "default) or predict over them without output correction "
                               "(skip)")
    estimate.add_argument("--samples", metavar="NAME|START:STOP|all", default=None,
                          help="the samples to estimate from: a segment of the model file's "
                               "[data.segments] by name, START:STOP (0-based, STOP excluded; "
                               "either may be left out) or all (default: the file's [data] "
                               "samples, else all); one record only")
    estimate.add_argument("--delimiter", choices=[",", ";", "tab"], default=None,
                          help="the CSV column separator (default: detected from the header; "
                               "a European Excel export uses ';' and a decimal comma)")
    estimate.add_argument("--no-progress", action="store_true",
                          help="no progress lines on stderr, only the final line of times "
                               "(as when stderr is not a terminal)")
    estimate.add_argument("-q", "--quiet", action="store_true",
                          help="nothing on stderr but warnings and errors: no progress, no "
                               "final line")
    estimate.add_argument("--summary", metavar="RUN.json", default=None,
                          help="also write the summary as JSON: θ̂ and its Cramér–Rao sd, "
                               "settling, status, the trust report, warnings, the method and "
                               "the ε and Γ the observer ran with (one record)")
    estimate.add_argument("--plot", metavar="FIG.png", default=None,
                          help="also write a figure of the estimates (one record; needs "
                               "matplotlib; " + ", ".join(PLOT_SUFFIXES) + ")")
    estimate.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                          help="fleet: run on this Dask cluster (default: in this process)")
    estimate.add_argument("--chunk-size", type=int, default=None,
                          help="fleet: records per task (default: about 16 tasks)")
    estimate.add_argument("--method", choices=ESTIMATION_METHODS, default=None,
                          help=f"estimator ({method_help()}; default: the model file's "
                               f"[estimator] method, else {ESTIMATION_METHODS[0]})")
    estimate.add_argument("--noise-std", metavar="SIGMA[,SIGMA...]", type=_noise_std,
                          default=None,
                          help="standard deviation of the output noise, one for every output "
                               "or one per output (default: estimated from the record, which "
                               "needs 12 samples; give it for shorter records)")
    estimate.set_defaults(run=_estimate,
                          check=lambda args: _estimate_positionals(args, estimate.error))


def _noise_std(text: str) -> list[float]:
    """--noise-std: one or more comma-separated numbers, finite and > 0."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(0.0 < v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"expected numbers > 0 separated by commas (e.g. "
                                         f"0.01, or 0.01,0.02 for two outputs); got {text!r}")
    return values


def _add_codegen(sub: _Subparsers) -> None:
    codegen = sub.add_parser(
        "codegen", help="generate the model file's estimator as C99",
        description="Generate a dependency-free C99 observer <name>.h/<name>.c (fixed dt, "
                    "no heap; the paper's estimator, [estimator] method = paper), a CSV "
                    "harness <name>_main.c and a Makefile (make -C DIR builds DIR/<name>, "
                    "which reads the CSV layout of `thetahat estimate` and writes its "
                    "columns). Prints the sizes of the state struct and of the constants. "
                    "--method ekf: the joint EKF on col(x, θ) instead (its harness reads "
                    "t,u…,y… rows and writes t,x̂…,θ̂…); --method guarded: the guarded "
                    "estimator without fits (stage 1, stage 2 and the guard; its harness "
                    "writes t,x̂…,θ̂…,θ̂_G…,θ̂₂…,δ…).")
    codegen.add_argument("model", help="model file (.toml or .json)")
    codegen.add_argument("--dt", type=float, required=True, help="fixed step length in s")
    codegen.add_argument("--eps", type=float, default=None,
                         help="ε of the gain design (default: the model file's)")
    codegen.add_argument("--gamma", type=float, nargs="+", default=None, metavar="G",
                         help="Γ of the update law: one number (G·I) or one per parameter "
                              "(the diagonal); default the model file's. For Gamma = "
                              "\"auto\" give the Γ `thetahat estimate` printed, or --data")
    codegen.add_argument("--data", metavar="LOG", default=None,
                         help="choose Gamma = \"auto\" on this record, as `thetahat "
                              "estimate` does (a CSV, Parquet, MATLAB or Excel file); "
                              "--method ekf: estimate σ and choose the RK4 sub-steps on it")
    codegen.add_argument("--delimiter", choices=[",", ";", "tab"], default=None,
                         help="--data's CSV column separator (default: detected)")
    codegen.add_argument("--real", choices=["double", "float"], default="double",
                         help="C type of every number (default: double)")
    codegen.add_argument("--name", default=None,
                         help="file stem and C prefix, a C identifier (default: the model "
                              "file's stem made one)")
    codegen.add_argument("--nan-policy", choices=["raise", "skip"], default="raise",
                         help="a NaN output sample: refused (raise, default), or predicted "
                              "over (skip)")
    codegen.add_argument("--hold", choices=["zoh", "foh", "smooth"], default="zoh",
                         help="sample hold; foh: the paper's <name>_step also takes the next "
                              "samples, the EKF's (and guarded's stage 2) the line from the "
                              "previous sample to the current one; smooth (ekf, guarded): "
                              "that line through samples corrected for a smooth input, the "
                              "statistical methods' default in estimate")
    codegen.add_argument("--method", choices=["paper", "ekf", "guarded"], default="paper",
                         help="the estimator: the paper's observer (default), the joint "
                              "EKF on col(x, θ) (stage 2; needs --noise-std or --data), "
                              "or guarded: both with the guard between them, "
                              "no re-anchoring fits (the paper's and the EKF's options)")
    codegen.add_argument("--noise-std", metavar="SIGMA[,SIGMA...]", type=_noise_std,
                         default=None, help="--method ekf or guarded: σ of the output noise "
                                            "(R = σ² I); default: estimated from --data")
    codegen.add_argument("-o", "--output", required=True, help="output folder")
    codegen.set_defaults(run=_codegen)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="thetahat",
        description="State, perturbation and parameter estimation for linear systems with "
                    "nonlinearly parameterized perturbations (Grip, Saberi & Johansen).",
        epilog=EXIT_CODES)
    parser.add_argument("--version", action="version", version=f"thetahat {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_demo, _add_sweep, _add_tune, _add_analyze, _add_estimate, _add_codegen):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``thetahat`` command; returns the exit code.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        See ``EXIT_CODES``: 0 success, 1 the model fails the theory's checks, 2 a usage or
        input error, 3 an internal error, 130 interrupted.
    """
    parser = _parser()
    try:
        args = parser.parse_args(argv)
        check = getattr(args, "check", None)            # what argparse cannot say alone
        if check is not None:
            check(args)
    except SystemExit as exc:              # --help, --version, or a usage error (code 2)
        return int(exc.code or 0)
    except BrokenPipeError:                # --help into a closed pipe
        if _reader_gone():
            return EXIT_PIPE
        raise
    try:
        code = args.run(args)
        sys.stdout.flush()                 # a reader that went away shows here, not at exit
        return code
    except BrokenPipeError as exc:         # EPIPE: the output's reader, or another pipe?
        if _reader_gone():
            return EXIT_PIPE
        _report(args, "error", exc)
        return EXIT_INPUT
    except _CHECK_ERRORS as exc:
        _report(args, "check failed", exc)
        return EXIT_CHECK
    except (ThetahatError, OSError) as exc:
        _report(args, "error", exc)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("thetahat: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # noqa: BLE001 - a bug: no traceback unless --debug
        _report(args, f"internal error ({type(exc).__name__}; a bug, please report it with "
                      f"the output of --debug)", exc)
        return EXIT_INTERNAL


def _report(args: argparse.Namespace, what: str, exc: BaseException) -> None:
    if args.debug:
        import traceback

        traceback.print_exception(exc, file=sys.stderr)
    print(f"thetahat: {what}: {exc}", file=sys.stderr)


def _reader_gone() -> bool:
    """Whether stdout or stderr is a pipe whose reader has closed it; those are then pointed at
    the null device, so that nothing written later (at exit, by a worker) fails again.

    A pipe with no reader polls as POLLERR (Linux, the BSDs); a file, a terminal or a pipe that
    is still read does not. Without ``select.poll`` (Windows, which has no SIGPIPE either) the
    error is reported as any other.
    """
    import select

    if not hasattr(select, "poll"):
        return False
    gone = False
    for stream in (sys.stdout, sys.stderr):
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):      # replaced (pytest's capture)
            continue
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        if any(events & select.POLLERR for _, events in poller.poll(0)):
            gone = True
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)
    return gone
