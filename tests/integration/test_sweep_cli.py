"""``fasthex sweep`` run the way a person runs it: in a pseudo-terminal that is its controlling
terminal, stopped with Ctrl-C (SIGINT to the whole foreground process group), SIGTERM to the
group (what ``timeout`` sends) or by closing the terminal (SIGHUP), then started again; and the
command's refusals.

A stopped sweep must say how many runs are in its table, exit 130 without a traceback, leave
no process behind (its workers, the forkserver, Dask's nannies and workers) and leave a
readable table with the rows it finished; the same command then flies only the missing runs.

The campaign: runs of the 1.6 s hop of ``test_sweep.py`` (2 gains x 2 tilts x its seeds): 8
where the sweep runs to its end, more where it is stopped, so that a stop sent after the first
runs cannot find every run already flown. The tests wait on what the terminal shows (the
progress line's count), not on time.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import pty
import re
import signal
import subprocess
import sys
import termios
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest
from terminal_support import screen

from groundstation.campaign import load_campaign
from groundstation.cli import main
from groundstation.sweep import TIMING_COLUMNS, ResultsTable, SerialRunner, died_row, sweep

HOP = """\
schema: fasthex.mission
version: 1
name: hop
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 1.0
    height_m: 0.3
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 0.6
  - kind: land
    duration_s: 3.0
"""

CAMPAIGN = """\
schema: fasthex.campaign
version: 1
name: hop-cli
mission: hop.yaml
preset: paper-calibrated
duration_s: 1.6
parameters:
  - path: vehicle.controller.ki_pos
    values: [10.0, 30.0]
  - path: run.tilt_deg
    values: [0.0, 30.0]
seeds: [0, 1]
"""

N_RUNS = 8  # the campaign as written by default: 4 points x 2 seeds
#: runs of the campaigns that are stopped before their end: a loaded host must not be able
#: to fly them all between the stop being sent and it taking effect (with 8, CI once did)
N_RUNS_STOPPED = 128
#: runs of the campaign stopped three times and then flown to its end (its tail is flown)
N_RUNS_RESUMED = 32
PROGRESS = re.compile(r"hop-cli \[[#.]+\] (\d+)/(\d+) runs")
INTERRUPTED = re.compile(r"fasthex: sweep interrupted: (\d+) of (\d+) runs are in (\S+) "
                         r"\((\d+) rows\)")
#: the environment variable every process of a sweep inherits (found again in /proc)
TAG = "FASTHEX_SWEEP_CLI_TEST"


def write_campaign(tmp_path: Path, n_runs: int = N_RUNS) -> Path:
    """The hop campaign (4 points) with as many seeds as give ``n_runs`` runs."""
    assert n_runs % 4 == 0
    (tmp_path / "hop.yaml").write_text(HOP)
    path = tmp_path / "hop-cli.yaml"
    path.write_text(CAMPAIGN.replace("seeds: [0, 1]", f"seeds: {list(range(n_runs // 4))}"))
    return path


def _take_terminal() -> None:
    """In the child: a new session whose controlling terminal is the pty on fd 0, and the stop
    signals as a shell leaves them for a foreground job (default action, not blocked)."""
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, (signal.SIGINT, signal.SIGTERM, signal.SIGHUP))


def processes_tagged(tag: str) -> list[int]:
    """The live processes whose environment carries ``TAG=tag`` (zombies have none)."""
    needle = f"{TAG}={tag}".encode()
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                if needle in (entry / "environ").read_bytes().split(b"\0"):
                    pids.append(int(entry.name))
    return pids


class TerminalSweep:
    """``fasthex sweep`` in a pty of its own: a session leader with the pty as its controlling
    terminal, as a shell runs it."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.tag = uuid.uuid4().hex
        self.master, slave = pty.openpty()
        env = dict(os.environ, **{TAG: self.tag})
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation", "sweep", *args], cwd=cwd, env=env,
            stdin=slave, stdout=slave, stderr=slave, preexec_fn=_take_terminal, close_fds=True)
        os.close(slave)
        self.output = bytearray()
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _drain(self) -> None:  # a terminal reads what the program writes
        while True:
            try:
                data = os.read(self.master, 4096)
            except OSError:
                data = b""
            with self._changed:
                self.output += data
                self._changed.notify_all()
            if not data:
                return

    @property
    def text(self) -> str:
        return self.output.decode(errors="replace")

    def wait_for_runs(self, n: int, timeout_s: float = 60.0) -> int:
        """Wait until the progress line counts at least ``n`` runs flown; that count."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                counts = [int(m.group(1)) for m in PROGRESS.finditer(self.text)]
                if counts and counts[-1] >= n:
                    return counts[-1]
                assert self.proc.poll() is None, self.text
                left = deadline - time.monotonic()
                assert left > 0, self.text
                self._changed.wait(timeout=min(left, 1.0))

    def type_ctrl_c(self) -> None:
        os.write(self.master, b"\x03")  # the line discipline signals the foreground group

    def signal_group(self, sig: int) -> None:
        os.killpg(self.proc.pid, sig)

    def hang_up(self) -> None:
        """Close the terminal: the kernel sends SIGHUP to the session's foreground group."""
        os.close(self.master)
        self.master = -1

    def wait(self, timeout_s: float = 60.0) -> int:
        try:
            return self.proc.wait(timeout=timeout_s)
        finally:
            self._reader.join(timeout=5)
            if self.master >= 0:
                os.close(self.master)

    def assert_no_process_left(self) -> None:
        # the forkserver and multiprocessing's resource tracker end when they read the end of
        # their pipe from the exited parent: bounded wait for that, nothing else
        deadline = time.monotonic() + 10.0
        while processes_tagged(self.tag) and time.monotonic() < deadline:
            time.sleep(0.05)
        left = processes_tagged(self.tag)
        for pid in left:  # the test fails, but leaves nothing running behind it
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        assert left == [], [_cmdline(pid) for pid in left]


def _cmdline(pid: int) -> str:
    try:
        return (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
                .decode(errors="replace")[:200])
    except OSError:
        return f"{pid} (gone)"


def same_bits(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Equal cell by cell, floats by their bits (NaN equal to NaN)."""
    return a.keys() == b.keys() and all(
        a[k].hex() == b[k].hex() if isinstance(a[k], float) and isinstance(b[k], float)
        else a[k] == b[k] for k in a)


def table_rows(path: Path) -> dict[str, dict[str, Any]]:
    rows = pq.read_table(path).to_pylist()
    return {r["run_id"]: {k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows}


def assert_interrupted_cleanly(sweep_: TerminalSweep, code: int, out: Path, at_least: int,
                               shown: bool = True, n_runs: int = N_RUNS_STOPPED,
                               ) -> dict[str, dict[str, Any]]:
    """Exit 130, the message naming the rows (when the terminal is there to show it), no
    traceback, nothing left running, and a readable table (no journal of parts left) holding
    the rows said, every one flown."""
    text = sweep_.text
    assert code == 130, text
    assert "Traceback" not in text and "Error" not in text, text
    sweep_.assert_no_process_left()
    assert not out.with_name(out.name + ".parts").exists()
    rows = table_rows(out)
    if shown:
        found = INTERRUPTED.search(text)
        assert found is not None, text
        in_table, total, name, n_rows = (int(found.group(1)), int(found.group(2)),
                                         found.group(3), int(found.group(4)))
        assert name == out.name and in_table == n_rows == len(rows) and total == n_runs
    assert at_least <= len(rows) < n_runs
    assert all(r["verdict"] == "ok" and r["error"] is None for r in rows.values()), rows
    return rows


def assert_screen(text: str, running_on: str, n_runs: int = N_RUNS_STOPPED) -> None:
    """What the terminal shows of an interrupted sweep: its four lines, the progress line
    once (rewritten in place), the message on a line of its own."""
    lines = screen(text)
    assert len(lines) == 4, lines
    assert lines[0].startswith(f"campaign hop-cli: {n_runs} runs (1 scenario(s) x 4 point(s) "
                               f"x {n_runs // 4} seed")
    assert lines[1] == running_on
    assert PROGRESS.match(lines[2]) and "runs/min, elapsed" in lines[2]
    assert INTERRUPTED.match(lines[3])


def test_that_a_pool_sweep_stops_cleanly_on_each_stop_signal_and_the_same_command_ends_it(
        tmp_path: Path) -> None:
    # Fixture: a campaign the three stops and the last sweep share
    n_runs = N_RUNS_RESUMED
    write_campaign(tmp_path, n_runs)
    out = tmp_path / "hop.parquet"
    command = ["hop-cli.yaml", "--workers", "2", "--out", out.name]

    # Test: Ctrl-C to the foreground process group once 2 runs are done
    first = TerminalSweep(command, tmp_path)
    seen = first.wait_for_runs(2)
    first.signal_group(signal.SIGINT)
    code = first.wait()
    # Assert
    rows_1 = assert_interrupted_cleanly(first, code, out, at_least=seen, n_runs=n_runs)
    # the progress line was rewritten in place: one line on the screen, drawn many times
    assert_screen(first.text, "running on 2 local worker processes", n_runs)
    assert first.text.count("\r\x1b[2K") >= 2

    # Test: the same command, SIGTERM to the group (timeout's way) once one more run is done
    second = TerminalSweep(command, tmp_path)
    second.wait_for_runs(1)
    second.signal_group(signal.SIGTERM)
    code = second.wait()
    # Assert: the rows of the first sweep kept as they were, more of them now
    assert f"{len(rows_1)} already in {out.name}, {n_runs - len(rows_1)} to fly" in second.text
    rows_2 = assert_interrupted_cleanly(second, code, out, at_least=len(rows_1) + 1,
                                        n_runs=n_runs)
    assert all(same_bits(rows_2[rid], row) for rid, row in rows_1.items())

    # Test: the same command, and the terminal closed (SIGHUP) once one more run is done
    third = TerminalSweep(command, tmp_path)
    third.wait_for_runs(1)
    third.hang_up()
    code = third.wait()
    # Assert
    rows_3 = assert_interrupted_cleanly(third, code, out, at_least=len(rows_2) + 1,
                                        shown=False, n_runs=n_runs)
    assert all(same_bits(rows_3[rid], row) for rid, row in rows_2.items())

    # Test: the same command once more, to the end
    last = TerminalSweep(command, tmp_path)
    code = last.wait()
    # Assert: only the missing runs flew
    text = last.text
    assert code == 0, text
    assert f"{len(rows_3)} already in {out.name}, {n_runs - len(rows_3)} to fly" in text
    assert (f"{out.name}: {n_runs} runs ({n_runs} ok); flew {n_runs - len(rows_3)} now, "
            f"{len(rows_3)} were already there") in text
    last.assert_no_process_left()
    rows = table_rows(out)
    assert len(rows) == n_runs and sorted(r["run_index"] for r in rows.values()) == list(
        range(n_runs))
    assert all(same_bits(rows[rid], row) for rid, row in rows_3.items())


@pytest.mark.exclusive  # a CI run with four busy workers saw Dask's shutdown outlast 60 s
def test_that_sigterm_twice_at_once_stops_a_sweep_as_one_stop(tmp_path: Path) -> None:
    """GNU ``timeout`` sends its signal to the command and then to its process group: the
    sweep gets SIGTERM twice (20 ms apart here: ``timeout`` preempted between its two sends on
    a loaded host). The second is the same stop, not a second interrupt in the middle of the
    first one's clean-up."""
    # Fixture
    write_campaign(tmp_path, N_RUNS_STOPPED)
    out = tmp_path / "hop.parquet"
    sweep_ = TerminalSweep(["hop-cli.yaml", "--workers", "2", "--out", out.name], tmp_path)
    seen = sweep_.wait_for_runs(1)
    # Test
    os.kill(sweep_.proc.pid, signal.SIGTERM)
    time.sleep(0.02)  # inside the repeat window (0.1 s), long enough to be delivered apart
    sweep_.signal_group(signal.SIGTERM)
    code = sweep_.wait()
    # Assert: stopped once, cleanly
    assert_interrupted_cleanly(sweep_, code, out, at_least=seen)
    assert sweep_.text.count("sweep interrupted") == 1, sweep_.text


def test_that_ctrl_c_stops_a_dask_local_cluster_sweep_without_dask_tracebacks(
        tmp_path: Path) -> None:
    # Fixture
    write_campaign(tmp_path, N_RUNS_STOPPED)
    out = tmp_path / "dask.parquet"
    # Test
    sweep_ = TerminalSweep(["hop-cli.yaml", "--workers", "2", "--scheduler", "local", "--out",
                            out.name], tmp_path)
    seen = sweep_.wait_for_runs(1)
    sweep_.type_ctrl_c()
    code = sweep_.wait()
    # Assert: our lines only: no Dask log lines, warnings or tracebacks from any process
    assert_interrupted_cleanly(sweep_, code, out, at_least=seen)
    assert_screen(sweep_.text, "running on Dask LocalCluster, 2 worker processes")


# -- refusals and the dry run ---------------------------------------------------------------


def test_that_a_campaign_file_error_is_one_line_with_file_line_and_key(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_campaign(tmp_path)
    path.write_text(CAMPAIGN.replace("path: run.tilt_deg", "path: rnu.tilt_deg"))
    assert main(["sweep", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fasthex: config error: {path}:10: parameters[1].path: expected "
                          "NAMESPACE.KEY"), err
    assert "'rnu.tilt_deg'" in err and err.count("\n") == 1


def test_that_a_campaign_value_out_of_range_names_its_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_campaign(tmp_path)
    path.write_text(CAMPAIGN.replace("duration_s: 1.6", "duration_s: -1"))
    assert main(["sweep", str(path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err == (f"fasthex: config error: {path}:6: duration_s: expected a number > 0 and "
                   "<= 3600, got -1\n")


@pytest.mark.parametrize("dry_run", [False, True])
def test_that_a_typo_in_a_parameter_path_is_refused_at_load_and_nothing_flies(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], dry_run: bool) -> None:
    path = write_campaign(tmp_path)
    path.write_text(CAMPAIGN.replace("vehicle.controller.ki_pos", "vehicle.controler.ki_pos"))
    out = tmp_path / "t.parquet"
    assert main(["sweep", str(path), "--out", str(out), *(["--dry-run"] if dry_run else [])]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"fasthex: config error: {path}:8: parameters[0].path: "
                                   "vehicle.controler: unknown key; expected one of: "), captured
    assert captured.err.count("\n") == 1 and captured.out == ""
    assert not out.exists() and not Path(f"{out}.parts").exists()


@pytest.mark.parametrize(("option", "value", "error"), [
    ("--workers", "0", "--workers must be at least 1, got 0"),
    ("--workers", "-3", "--workers must be at least 1, got -3"),
    ("--flush-s", "-1", "--flush-s must be between 0 and 3600 seconds, got -1.0"),
    ("--flush-s", "nan", "--flush-s must be between 0 and 3600 seconds, got nan"),
    ("--flush-s", "4000", "--flush-s must be between 0 and 3600 seconds, got 4000.0"),
])
def test_that_an_option_out_of_range_is_one_line_and_exit_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str,
        error: str) -> None:
    path = write_campaign(tmp_path)
    assert main(["sweep", str(path), option, value]) == 2
    assert capsys.readouterr().err == f"fasthex: {error}\n"


@pytest.mark.parametrize(("value", "why"), [
    ("garbage", ""),  # was a 30-line Dask traceback ('missing port number'), exit 1
    ("tcp://:99999", "; the port must be 1 .. 65535"),  # was the 20 s connect timeout
    ("tcp://host:0", "; the port must be 1 .. 65535"),
    ("", ""),  # was a silent run on the local pool
    ("tls://host:8786", ""),
])
def test_that_a_scheduler_not_local_or_tcp_host_port_is_one_line_before_anything(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str, why: str) -> None:
    path = write_campaign(tmp_path)
    # --dry-run: refused before the campaign's runs are even listed
    assert main(["sweep", str(path), "--scheduler", value, "--dry-run"]) == 2
    assert capsys.readouterr() == ("", f"fasthex: --scheduler {value!r}: expected 'local' or "
                                       f"tcp://HOST:PORT{why}\n")


def test_that_the_documented_scheduler_forms_are_accepted() -> None:
    from groundstation.sweep import check_scheduler

    for value in ("local", "tcp://10.0.0.5:8786", "tcp://sched.lab:1", "tcp://[::1]:65535"):
        assert check_scheduler(value) == value


def runs_not_flown(monkeypatch: pytest.MonkeyPatch) -> list[int | None]:
    """``sweep``'s runner in this process, giving each run an error row instead of flying it;
    the list gets the worker count each runner was made for."""
    import groundstation.sweep as sweep_mod

    asked: list[int | None] = []

    def fake_runner(n: int | None, scheduler: str | None, *,
                    in_process: bool | None = None) -> SerialRunner:
        asked.append(n)
        assert not in_process  # capped to one, still a worker process
        runner = SerialRunner(lambda spec: died_row(spec, "not flown"))
        runner.description = f"{n} local worker processes"
        return runner

    monkeypatch.setattr(sweep_mod, "make_runner", fake_runner)
    return asked


def test_that_an_unreadable_part_is_set_aside_and_its_runs_fly_again(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: a sweep killed outright after journaling 4 parts of one row each, one of them
    # cut short (`truncate -s 100`): every resume used to stop at 'Parquet magic bytes not
    # found', exit 2
    path = write_campaign(tmp_path)
    out = tmp_path / "t.parquet"
    table = ResultsTable(out, {"campaign": "hop-cli"}, flush_interval_s=0.0)
    runs = list(load_campaign(path).runs())
    for run in runs[:4]:
        table.add(died_row(run, "flown before"))
    parts = sorted(table.parts_dir.glob("part-*.parquet"))
    assert len(parts) == 4
    os.truncate(parts[1], 100)
    runs_not_flown(monkeypatch)
    # Test: the dry run only reports it
    assert main(["sweep", str(path), "--out", str(out), "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"note: an unreadable part of the results table {parts[1]} (")
    assert err.splitlines()[0].endswith("; a sweep sets it aside and flies its runs again")
    assert parts[1].exists()
    # the sweep sets it aside and flies its run again
    assert main(["sweep", str(path), "--out", str(out), "--workers", "2"]) == 0
    err = capsys.readouterr().err
    corrupt = parts[1].with_name(parts[1].name + ".corrupt")
    assert err.startswith(f"note: an unreadable part of the results table {corrupt} (")
    assert "Parquet magic bytes not found" in err.splitlines()[0]
    assert err.splitlines()[0].endswith("; set aside, its runs fly again")
    assert "3 already in" in err and "5 to fly" in err
    # Assert: every run in the table; the corrupt part kept for a look, the others gone
    rows = table_rows(out)
    assert set(rows) == {r.run_id for r in runs}
    assert rows[runs[1].run_id]["error"] == "not flown"
    assert rows[runs[0].run_id]["error"] == "flown before"
    assert sorted(table.parts_dir.iterdir()) == [corrupt]
    assert corrupt.stat().st_size == 100


def test_that_parts_and_the_table_are_fsynced_before_their_rename(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: os.fsync and os.replace record what they were given (a file by its /proc name)
    events: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src: Any, dst: Any) -> None:
        events.append(("replace", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    path = write_campaign(tmp_path)
    table = ResultsTable(tmp_path / "t.parquet", {"campaign": "hop-cli"}, flush_interval_s=0.0)
    # Test
    table.add(died_row(next(iter(load_campaign(path).runs())), "x"))
    (part,) = table.parts_dir.glob("part-*.parquet")
    table.consolidate()
    # Assert: the data reach the disk before the name does (a power loss between the two left
    # a truncated part under its final name), then the folder's entry
    parts_dir = str(table.parts_dir.resolve())
    assert events == [("fsync", str(part.resolve()) + ".tmp"), ("replace", str(part)),
                      ("fsync", parts_dir),
                      ("fsync", str((tmp_path / "t.parquet.tmp").resolve())),
                      ("replace", str(tmp_path / "t.parquet")),
                      ("fsync", str(tmp_path.resolve()))]


@pytest.mark.parametrize(("cpus", "workers", "started", "note"), [
    (16, "1000", 8, " (--workers 1000 capped at the 8 run(s) to fly)"),
    (1, "1000", 4, " (--workers 1000 capped at 4 per core on 1 core(s))"),
    (16, "3", 3, ""),
    (16, None, 8, ""),  # the default, every core, is capped at the runs without a note
    (16, "1000", 1, " (--workers 1000 capped at the 1 run(s) to fly)"),
])
def test_that_workers_are_capped_at_the_runs_to_fly_and_per_core(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        cpus: int, workers: str | None, started: int, note: str) -> None:
    # Fixture: an 8-run campaign (7 already flown for the last case); the runner is
    # recorded, the runs are not flown
    path = write_campaign(tmp_path)
    if started == 1:
        table = ResultsTable(tmp_path / "t.parquet", {"campaign": "hop-cli"})
        for run in list(load_campaign(path).runs())[1:]:
            table.add(died_row(run, "flown before"))
        table.consolidate()
    asked = runs_not_flown(monkeypatch)
    monkeypatch.setattr(os, "cpu_count", lambda: cpus)
    # Test (--workers 1000 used to start 1000 processes for 8 runs)
    assert main(["sweep", str(path), "--out", str(tmp_path / "t.parquet"),
                 *(["--workers", workers] if workers else [])]) == 0
    # Assert
    assert asked == [started]
    assert f"running on {started} local worker processes{note}\n" in capsys.readouterr().err


def test_that_sweep_report_without_a_table_says_what_it_needs(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sweep", "report"]) == 2
    assert capsys.readouterr().err == ("fasthex: sweep report needs the results table: "
                                       "fasthex sweep report TABLE\n")


def test_that_the_dry_run_lists_every_run_as_done_or_todo_after_a_partial_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: 2 of the 8 runs flown into the table (the first and the last)
    from groundstation.campaign import load_campaign

    path = write_campaign(tmp_path)
    out = tmp_path / "partial.parquet"
    campaign = load_campaign(path)
    runs = list(campaign.runs())
    table = ResultsTable(out, {"campaign": campaign.name,
                               "parameters": campaign.parameter_names()})
    assert sweep([runs[0], runs[7]], table, SerialRunner()) == (2, 0)
    before = out.read_bytes()
    # Test
    assert main(["sweep", str(path), "--out", str(out), "--dry-run"]) == 0
    # Assert: one line per run in campaign order, its state and point; nothing flown
    captured = capsys.readouterr()
    assert f"2 already in {out}, 6 to fly" in captured.err
    lines = captured.out.splitlines()
    assert len(lines) == N_RUNS
    for run, line in zip(runs, lines, strict=True):
        index, run_id, state, scenario, seed, *point = line.split()
        assert (int(index), run_id) == (run.run_index, run.run_id)
        assert state == ("done" if run.run_index in (0, 7) else "todo")
        assert scenario == "scenario=none" and seed == f"seed={run.seed}"
        assert " ".join(point) == ", ".join(f"{k}={v}" for k, v in run.params.items())
    assert lines[0].split()[4:] == ["seed=0", "vehicle.controller.ki_pos=10.0,",
                                    "run.tilt_deg=0.0"]
    assert out.read_bytes() == before
    assert not math.isnan(float(pq.read_table(out).column("sim_time_s")[0].as_py()))
