"""No traceback, ever (issue 14, item 6): every sub-command, run as a user runs it (a subprocess), on hostile
arguments -- missing files, directories, empty files, garbage CSV and YAML, a text file as database, data too
short to diagnose -- and with its output going to a reader that has already gone. It fails on any traceback, on
the last line of defence being reached (a cause left unfixed), and on an exit code the README does not list."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import redirect_stderr
from dataclasses import dataclass
from pathlib import Path

import pytest

import labrunner
from labrunner.campaign_csv import write_campaign
from labrunner.cli import EXIT_BROKEN_PIPE, build_parser, main, subparsers
from labrunner.sims.campaign import CampaignPlan, synthesize

EXIT_CODES = {0, 1, 2, 3, 4, EXIT_BROKEN_PIPE}  # README, "Commands"
BAD_INPUT = 2
COMMANDS = {name for name, _ in subparsers(build_parser())}

MINI = """\
name: mini
temperatures: {list_c: [25]}
soak: {tolerance_c: 0.5, stable_window_s: 60, max_wait_s: 3600, on_timeout: continue, poll_s: 30}
orientations: [z_up]
remount_s: 10
rates: {list_dps: [0, 50]}
settle_s: 1
record_s: 6
record_poll_s: 3
fit: {run: false}
"""


@dataclass(frozen=True)
class Case:
    argv: tuple[str, ...]
    names: str | None = None  # the path the message must name (bad input), or None: any documented exit
    closed_stdout: bool = False  # stdout is a pipe whose reader is already gone

    @property
    def command(self) -> str:
        words = [a for a in self.argv if not a.startswith("-")]
        return " ".join(words[:2]) if words[:1] == ["sim"] else (words[0] if words else "--help")


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("hostile")
    (d / "somedir").mkdir()
    (d / "dir.yaml").mkdir()  # a directory named like the file it should be
    (d / "dir.csv").mkdir()
    (d / "empty.csv").write_text("")
    (d / "empty.yaml").write_text("")
    (d / "garbage.csv").write_bytes(b"t_s;run\x00\xff\xfe\n1;2;3;4\n\x89PNG\r\n")
    (d / "header.csv").write_text("t_s,run,orientation\n1,2\n")
    (d / "garbage.yaml").write_text("name: [unclosed\n  - : :\n\t tab\n")
    (d / "list.yaml").write_text("- just\n- a list\n")
    (d / "text.db").write_text("this is a text file, not a database\n")
    (d / "mini.yaml").write_text(MINI)
    (d / "file").write_text("a file where a directory is expected\n")
    labrunner.run(d / "mini.yaml", db=d / "mini.db")
    # 200 valid rows of one short record: too little for the diagnosis's held-out stretches.
    plan = CampaignPlan(orientations=("z_up",), temperatures_c=(25.0,), rates_dps=(0.0, 50.0), record_s=4.0,
                        settle_s=1.0, sample_rate_hz=50.0, soak_window_s=30.0, soak_max_s=60.0)
    write_campaign(synthesize(plan).head(200), d / "short.csv")
    return d


def _cases() -> Iterator[Case]:
    def bad(*argv: str, names: str) -> Case:
        return Case(tuple(argv), names=names)

    run = ("--sim", "--db", "new.db")
    yield bad("run", "missing.yaml", *run, names="missing.yaml")
    yield bad("run", "somedir", *run, names="somedir")
    yield bad("run", "mini.yaml", "--lab", "dir.yaml", "--db", "new.db", names="dir.yaml")
    yield bad("run", "mini.yaml", "--sim", "--sim-config", "list.yaml", "--db", "new.db", names="list.yaml")
    yield bad("run", "mini.yaml", "--sim", "--db", "text.db", names="text.db")
    yield bad("run", "mini.yaml", "--sim", "--db", "somedir", names="somedir")
    for db in ("missing.db", "text.db", "somedir"):
        yield bad("status", db, names=db)
    for db in ("text.db", "somedir"):
        yield bad("resume", db, names=db)
    yield bad("abort", "text.db", names="text.db")
    yield bad("export", "text.db", "--csv", "out.csv", names="text.db")
    yield bad("export", "mini.db", "--csv", "somedir", names="somedir")
    yield bad("export", "mini.db", "--csv", "nodir/out.csv", names="nodir")
    for path in ("dir.yaml", "empty.yaml", "garbage.yaml"):  # `run` reads a procedure as `check` does
        yield bad("check", path, names=path)
    yield bad("check", "--lab", "garbage.yaml", names="garbage.yaml")
    yield bad("check", "--sim-config", "somedir", names="somedir")
    for path in ("garbage.csv", "dir.csv"):
        yield bad("check", "--csv", path, names=path)
    for data in ("somedir", "garbage.csv", "text.db"):
        yield bad("fit", data, "--quiet", names=data)
    yield bad("fit", "mini.db", "--quiet", "--no-store", "--out", "file", names="file")
    yield bad("fit", "mini.db", "--quiet", "--no-store", "--json", "somedir", names="somedir")
    for data in ("somedir", "short.csv", "header.csv"):
        yield bad("diagnose", data, "--json", "d.json", names=data)
    for model in ("somedir", "garbage.csv", "missing.json"):  # a model file of another format, or none
        yield bad("compensate", model, "short.csv", "--csv", "c.csv", names=model)
    yield bad("compensate", "garbage.csv", "header.csv", "--csv", "c.csv", names="garbage.csv")
    yield bad("sim", "serve", "--config", "somedir", "--duration", "0.1", names="somedir")
    # Values out of range, once errors from deep inside (bind, the profile table, numpy's seed, sleep).
    yield bad("sim", "serve", "--chamber-port", "99999", names="--chamber-port")
    yield bad("sim", "serve", "--profile", "bogus", "--duration", "0.1", names="bogus")
    yield bad("sim", "serve", "--host", "999.1.1.1", "--duration", "0.1", names="999.1.1.1")
    yield bad("run", "mini.yaml", "--sim", "--db", "new.db", "--seed", "-1", names="--seed")
    yield bad("status", "mini.db", "--watch", "-1", names="--watch")
    if "list" in COMMANDS:
        yield bad("list", "text.db", names="text.db")
    if "report" in COMMANDS:
        yield bad("report", "text.db", "--html", "r.html", names="text.db")
        yield bad("report", "mini.db", "--html", "somedir", names="somedir")
    if "report" in COMMANDS:
        yield bad("report", "text.db", "--html", "r.html", names="text.db")
        yield bad("report", "mini.db", "--html", "somedir", names="somedir")
        yield bad("report", "mini.db", "--html", "nodir/r.html", names="nodir")
        yield bad("report", "mini.db", "--campaign", "-1", "--html", "r.html", names="--campaign")
    # The reader is gone before the first byte: every write hits a closed pipe, deterministically.
    for argv in (("--help",), ("status", "mini.db"), ("export", "mini.db", "--csv", "-", "--with-monitor"),
                 ("check", "mini.yaml"), ("fit", "mini.db", "--json", "-", "--quiet", "--no-store"),
                 ("resume", "mini.db"), ("status", "mini.db", "--watch", "0.1"),
                 ("sim", "serve", "--duration", "0.2"), *((("list", "mini.db"),) if "list" in COMMANDS else ()),
                 *((("report", "mini.db", "--html", "mini.html"),) if "report" in COMMANDS else ())):
        yield Case(argv, closed_stdout=True)


CASES = list(_cases())


def _run(case: Case, cwd: Path) -> subprocess.CompletedProcess[str]:
    stdout: int = subprocess.PIPE
    read_end = None
    if case.closed_stdout:
        read_end, stdout = os.pipe()
        os.close(read_end)
    try:
        return subprocess.run([sys.executable, "-m", "labrunner", *case.argv], cwd=cwd, stdout=stdout,
                              stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        if case.closed_stdout:
            os.close(stdout)


def test_every_command_is_exercised() -> None:
    assert COMMANDS <= {c.command for c in CASES} | {"sim"}, "a sub-command without a hostile case"


def test_hostile_arguments_and_closed_pipes(lab: Path) -> None:
    # Subprocesses in parallel (each mostly imports): the whole set in well under a minute.
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda c: (c, _run(c, lab)), CASES))
    problems = []
    for case, proc in results:
        label = f"labrunner {' '.join(case.argv)}" + (" > closed pipe" if case.closed_stdout else "")
        err = proc.stderr
        if "Traceback" in err or "Exception ignored" in err:
            problems.append(f"{label}: traceback\n{err[-1500:]}")
        elif "this is a bug" in err:
            problems.append(f"{label}: reached the last line of defence: {err.strip()}")
        elif proc.returncode not in EXIT_CODES:
            problems.append(f"{label}: exit code {proc.returncode}\n{err[-500:]}")
        elif case.closed_stdout and (proc.returncode not in (0, EXIT_BROKEN_PIPE) or err.strip()):
            problems.append(f"{label}: not quiet (exit {proc.returncode}): {err.strip()[:300]}")
        elif case.names is not None and (proc.returncode != BAD_INPUT or err.count("error:") != 1
                                         or case.names not in err.strip().splitlines()[-1]):
            problems.append(f"{label}: expected one located message naming {case.names} and exit 2, got exit "
                            f"{proc.returncode}: {err.strip()[:400]}")
    assert not problems, "\n\n".join(problems)


def test_short_data_gets_a_located_message(lab: Path) -> None:
    proc = _run(Case(("diagnose", "short.csv", "--json", "d.json")), lab)
    assert proc.returncode == BAD_INPUT
    message = proc.stderr.strip()
    assert message.startswith("labrunner diagnose: error: short.csv: too little data to diagnose: 200 rows over 4 s")
    assert "needs data in at least 2" in message


def test_directories_are_named_as_such(lab: Path) -> None:
    for argv, path in ((("fit", "somedir", "--quiet"), "somedir"), (("check", "dir.yaml"), "dir.yaml"),
                       (("run", "somedir", "--sim", "--db", "x.db"), "somedir")):
        code, err = _in_process(lab, argv)
        assert code == BAD_INPUT and f"{path}: is a directory; expected a" in err, err


def _in_process(cwd: Path, argv: tuple[str, ...]) -> tuple[int, str]:
    err = io.StringIO()
    old = Path.cwd()
    os.chdir(cwd)
    try:
        with redirect_stderr(err):
            code = main(list(argv))
    finally:
        os.chdir(old)
    return code, err.getvalue()


def test_last_line_of_defence(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """An unexpected exception is one line naming the command, exit 1; its traceback only at DEBUG."""
    import labrunner.commands.campaign as campaign

    def broken(_args: object) -> int:
        raise RuntimeError("the flux capacitor is unplugged")

    monkeypatch.setattr(campaign, "cmd_status", broken)
    code, err = _in_process(tmp_path, ("status", "x.db"))
    assert code == 1
    assert err.strip() == ("labrunner status: error: RuntimeError: the flux capacitor is unplugged; this is a bug: "
                           "please report it with `-v --log-level DEBUG` output")
    code, err = _in_process(tmp_path, ("--log-level", "DEBUG", "status", "x.db"))
    assert code == 1 and "Traceback" in err and "the flux capacitor" in err.splitlines()[-1]


def test_a_path_the_system_refuses_is_bad_input(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """An OSError naming a file (permissions, a directory, a missing folder) reaching the CLI is the user's
    path: exit 2 and the path, not a bug report."""
    import labrunner.commands.campaign as campaign

    def refused(_args: object) -> int:
        raise PermissionError(13, "Permission denied", "/lab/locked.db")

    monkeypatch.setattr(campaign, "cmd_status", refused)
    code, err = _in_process(tmp_path, ("status", "x.db"))
    assert (code, err.strip()) == (2, "labrunner status: error: /lab/locked.db: permission denied")


LONG = """\
name: long
temperatures: {list_c: [15, 25, 35]}
soak: {tolerance_c: 0.5, stable_window_s: 60, max_wait_s: 3600, on_timeout: continue, poll_s: 30}
orientations: [z_up, z_down]
remount_s: 10
rates: {triangular: {max_dps: 100, step_dps: 10}}
settle_s: 1
record_s: 2
record_poll_s: 2
fit: {run: false}
"""


def test_a_closed_stderr_does_not_end_a_run(lab: Path) -> None:
    """`labrunner run ... 2>&1 | head` once aborted the campaign (the progress bar's BrokenPipeError, raised
    in the sequencer's progress callback, was a fault). The display goes; the campaign goes on to the end."""
    (lab / "long.yaml").write_text(LONG)
    proc = subprocess.Popen([sys.executable, "-m", "labrunner", "run", "long.yaml", "--sim", "--db", "long.db"],
                            cwd=lab, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    first = proc.stderr.read(100)  # the plan line; the bar's updates come after it, into a closed pipe
    proc.stderr.close()
    assert proc.wait(timeout=120) == EXIT_BROKEN_PIPE  # the summary at the end found the pipe closed
    assert b"240 steps" in first
    status = labrunner.status(lab / "long.db")
    assert (status.status, status.steps_done, status.faults) == ("done", 240, 0)


class _PipeThatCloses(io.StringIO):
    """stderr whose reader leaves: writes fail with EPIPE once `gone`."""

    gone = False

    def write(self, text: str) -> int:
        if self.gone:
            raise BrokenPipeError(32, "Broken pipe")
        return super().write(text)

    def flush(self) -> None:
        if self.gone:
            raise BrokenPipeError(32, "Broken pipe")


def test_the_progress_bar_goes_quiet_when_its_reader_leaves(monkeypatch: pytest.MonkeyPatch) -> None:
    from labrunner.api import Progress
    from labrunner.commands.progress import ProgressBar

    stream = _PipeThatCloses()
    monkeypatch.setattr(sys, "stderr", stream)
    bar = ProgressBar(10, quiet=False)
    bar.bar.mininterval, bar.bar.miniters = 0.0, 1  # draw on every update, as a slow real run does
    bar(Progress(steps_done=1, steps_total=10, state="recording", step=None, lab_time_s=60.0))
    assert "1/10 steps" in stream.getvalue()
    stream.gone = True
    for done in range(2, 11):  # every update after the reader left: none raises into the sequencer
        bar(Progress(steps_done=done, steps_total=10, state="recording", step=None, lab_time_s=60.0 * done))
    assert bar.bar is None  # switched off at the first failed draw
    bar.close()
    stream.gone = True
    assert ProgressBar(10, quiet=False).bar is None  # gone before the first draw
