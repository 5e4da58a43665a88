"""Progress a person sees: :class:`thetahat.progress.Stages`, and ``thetahat estimate`` in a
pseudo-terminal, piped, and with --quiet."""

from __future__ import annotations

import io
import os
import pty
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from thetahat.errors import OptionError, ThetahatError
from thetahat.progress import MODES, Stages

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SRC = Path(__file__).resolve().parents[1] / "src"

#: A person must see something within this time of starting the command (s): the issue's
#: bound. The first line is drawn before the model's libraries load (0.15 s measured on a
#: loaded 2-core machine), so the bound leaves a margin of ten.
#: The live line's redraw period used in the unit tests (s): short, so a test waits little.
FAST_REFRESH = 0.01
#: Models of the command-line tests: LuGre and three other shipped models (two outputs for the
#: two-inertia drive, a 10 Hz heater, Proposition 3's monotone law).
MODELS = ["lugre", "prop3", "heater", "two_inertia"]
#: Seconds of each model's scenario simulated for the command-line tests: a few thousand
#: samples, enough for every stage to run, few enough for a test.
T_END = {"lugre": 3.0, "prop3": 20.0, "heater": 400.0, "two_inertia": 20.0}
#: The stages `thetahat estimate` names, in order, with the default method ("guarded": its
#: fits are a stage of their own; the plan names them once the model file is loaded).
STAGE_NAMES = ("load model", "read", "estimate", "fits", "trust report", "write")

_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _screen(raw: str) -> list[str]:
    """What a terminal shows of ``raw``: each line as its last redraw left it."""
    lines = []
    for line in _ANSI.sub("", raw).replace("\r\n", "\n").split("\n"):
        lines.append(line.split("\r")[-1])
    return [line for line in lines if line]


# --- Stages ----------------------------------------------------------------------------------

def test_live_stages_are_named_numbered_timed_and_end_with_the_totals():
    out = io.StringIO()
    with Stages(("read", "estimate", "write"), stream=out, mode="live",
                refresh=FAST_REFRESH) as stages:
        stages.stage("read")
        stages.note("1,000 rows")
        stages.stage("estimate", total=1000)
        stages(250, 1000)
        time.sleep(5 * FAST_REFRESH)             # the drawing thread redraws the live line
        stages(1000, 1000)
        stages.stage("write")
    raw = out.getvalue()
    assert "thetahat: [2/3] estimate · 250/1,000 samples (25 %)" in raw
    assert "left" in raw.split("250/1,000")[1].split("\r")[0]    # an estimate of the rest
    screen = _screen(raw)
    assert [line.split(" · ")[0] for line in screen[:3]] == [
        "thetahat: [1/3] read", "thetahat: [2/3] estimate", "thetahat: [3/3] write"]
    assert screen[0].split(" · ")[1] == "1,000 rows"
    assert screen[1].split(" · ")[1] == "1,000 samples"          # the count, without total
    assert re.fullmatch(r"thetahat: done in \d+\.\d s: read \d+\.\d s, estimate \d+\.\d s, "
                        r"write \d+\.\d s", screen[3])
    assert len(screen) == 4
    assert [t.name for t in stages.times] == ["read", "estimate", "write"]
    assert all(t.seconds >= 0 for t in stages.times)
    assert stages.times[1].seconds >= 5 * FAST_REFRESH           # the sleep was in estimate


def test_fits_are_counted_and_the_time_left_comes_from_them():
    out = io.StringIO()
    with Stages(stream=out, mode="live", refresh=FAST_REFRESH) as stages:
        stages.stage("estimate", total=10_000)
        stages(10_000, 10_000)                   # samples done: no time left from them
        stages.fits(3, 12)
        time.sleep(5 * FAST_REFRESH)
    last = out.getvalue().split("3/12 fits (25 %)")[1].split("\r")[0]
    assert "left" in last
    seconds = float(re.search(r"about (\d+\.\d) s left", last).group(1))
    spent = float(re.search(r"· (\d+\.\d) s ·", "· " + last).group(1))
    # 3 of 12 fits took `spent`: 9 more take 3 × spent (both rounded to 0.1 s)
    assert seconds == pytest.approx(3 * spent, abs=0.35)


def test_final_mode_writes_one_line_and_quiet_nothing():
    for mode, lines in (("final", 1), ("quiet", 0)):
        out = io.StringIO()
        with Stages(("a", "b"), stream=out, mode=mode) as stages:
            stages.stage("a", total=10)
            stages(5, 10)
            stages.stage("b")
        text = out.getvalue()
        assert text.count("\n") == lines and "\r" not in text
        if lines:
            assert text.startswith("thetahat: done in ") and ": a " in text and ", b " in text


def test_auto_is_final_off_a_terminal():
    stages = Stages(stream=io.StringIO())
    assert stages.mode == "final"


def test_an_error_ends_the_live_line_and_writes_no_totals():
    out = io.StringIO()
    with pytest.raises(ThetahatError):
        with Stages(stream=out, mode="live", refresh=FAST_REFRESH) as stages:
            stages.stage("estimate", total=100)
            raise ThetahatError("boom")
    text = out.getvalue()
    assert text.endswith("\n") and "done in" not in text
    out = io.StringIO()
    with pytest.raises(ThetahatError):
        with Stages(stream=out, mode="final") as stages:
            stages.stage("estimate")
            raise ThetahatError("boom")
    assert out.getvalue() == ""


def test_a_closed_stream_never_fails_the_job():
    out = io.StringIO()
    with Stages(stream=out, mode="live", refresh=FAST_REFRESH) as stages:
        stages.stage("estimate")
        out.close()
        time.sleep(3 * FAST_REFRESH)
        stages.stage("write")
    assert [t.name for t in stages.times] == ["estimate", "write"]


def test_unknown_mode_is_refused():
    with pytest.raises(OptionError, match="unknown mode 'loud'"):
        Stages(mode="loud")
    assert MODES == ("auto", "live", "final", "quiet")


# --- the command -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def records(tmp_path_factory) -> dict[str, Path]:
    """A CSV record simulated from each model's scenario, under the model's signal names."""
    from thetahat.io.datafile import write_csv_table
    from thetahat.modelfile import load_model
    from thetahat.modelfile.study import simulate_model

    folder = tmp_path_factory.mktemp("records")
    paths = {}
    for name in MODELS:
        spec = load_model(EXAMPLES / f"{name}.toml")
        data = simulate_model(spec, seed=1, t_end=T_END[name])
        columns = {"t": data.t}
        columns.update({n: data.u[:, i] for i, n in enumerate(spec.layout.input_names)})
        columns.update({n: data.y[:, i] for i, n in enumerate(spec.layout.output_names)})
        paths[name] = folder / f"{name}.csv"
        write_csv_table(paths[name], columns)
    return paths


def _env() -> dict[str, str]:
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{path}" if path else str(SRC)}


def _in_a_terminal(argv: list[str], cwd: Path) -> tuple[int, float | None, str, str]:
    """Run ``python -m thetahat argv`` with a pseudo-terminal as stderr: the exit code, when
    the terminal got its first bytes (s after the start), what it got, and stdout."""
    master, slave = pty.openpty()
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "thetahat", *argv], cwd=cwd, env=_env(),
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=slave)
    os.close(slave)
    first, chunks = None, []
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    data = os.read(master, 65536)
                except OSError:                  # the child closed the terminal (Linux: EIO)
                    break
                if not data:
                    break
                if first is None:
                    first = time.monotonic() - start
                chunks.append(data)
            elif proc.poll() is not None:
                break
        stdout = proc.communicate(timeout=300)[0].decode()
    finally:
        os.close(master)
    return proc.returncode, first, b"".join(chunks).decode(errors="replace"), stdout


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.needs_speed
def test_estimate_in_a_terminal_names_its_stages_from_the_start(tmp_path, records, model):
    code, first, raw, stdout = _in_a_terminal(
        ["estimate", str(EXAMPLES / f"{model}.toml"), str(records[model]), "-o", "est.csv"],
        tmp_path)
    assert code == 0, raw
    # the first thing drawn, before the model is loaded (the numerical libraries' imports):
    # how soon is benchmarks/bench_estimate.py's to print (a time is no test's to assert)
    assert first is not None
    assert raw.startswith("\rthetahat: [1/5] load model")     # the method is not known yet
    screen = _screen(raw)
    assert [line.split(" · ")[0] for line in screen[:6]] == [
        f"thetahat: [{k}/6] {name}" for k, name in enumerate(STAGE_NAMES, 1)]
    # the fits' stage ends with the count of the fits made (> 0 on these records)
    assert re.fullmatch(r"[1-9]\d* fits", screen[3].split(" · ")[1])
    rows = sum(1 for _ in records[model].open()) - 1
    assert screen[1].split(" · ")[1] == f"{rows:,} rows"
    assert screen[-1].startswith("thetahat: done in ")
    assert "wrote est.csv" in stdout and (tmp_path / "est.csv").exists()


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.needs_speed
def test_estimate_piped_writes_one_final_line(tmp_path, records, model):
    proc = subprocess.run([sys.executable, "-m", "thetahat", "estimate",
                           str(EXAMPLES / f"{model}.toml"), str(records[model]), "-o",
                           "est.csv"], cwd=tmp_path, env=_env(), capture_output=True,
                          text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line]
    assert len(lines) == 1 and "\r" not in proc.stderr
    # a duration as progress._seconds writes it: "4.2 s", or "1 min 19 s" from a minute on
    took = r"(?:[\d.]+ s|\d+ min \d\d s)"
    assert re.fullmatch(rf"thetahat: done in {took}: " + ", ".join(
        rf"{name} {took}" for name in STAGE_NAMES), lines[0])


def test_estimate_quiet_writes_nothing_on_stderr(tmp_path, records):
    code, first, raw, stdout = _in_a_terminal(
        ["estimate", str(EXAMPLES / "lugre.toml"), str(records["lugre"]), "-o", "est.csv",
         "--quiet"], tmp_path)
    assert code == 0 and raw == "" and first is None
    assert "wrote est.csv" in stdout
