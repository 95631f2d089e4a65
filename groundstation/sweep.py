"""Running a campaign's flights in parallel and keeping every result: ``fasthex sweep``.

**Where runs execute** (a :class:`Runner`, chosen by :func:`make_runner`):

- ``workers == 1`` and no scheduler: in this process, one after the other;
- ``workers > 1`` (default: every core): a pool of worker processes this module starts
  (forked from a ``forkserver`` that imported the flight code), one run at a time each. A
  worker that dies (a segfault, the OOM killer) costs exactly the run it was flying: that
  run's row says so, a fresh worker takes its place;
- ``fasthex sweep`` caps the local workers (pool or ``local``) at the runs left to fly and
  :data:`MAX_WORKERS_PER_CPU` per core (:func:`local_workers`);
- ``scheduler`` ``local``: a Dask ``LocalCluster`` of ``workers`` single-threaded processes;
  ``tcp://HOST:8786``: the Dask distributed cluster behind that scheduler. Both are the same
  code (:class:`DaskRunner` on a ``distributed.Client``); a worker that dies is retried by Dask
  on another worker and, after Dask's ``allowed-failures``, is a row with the reason.

**The table** (:class:`ResultsTable`): one Parquet file, one row per run: identity
(``run_id``, ``run_index``, ``campaign``, ``seed``, ``scenario``), the parameter columns (named
by their dotted path), every key of ``fasthex simulate --json`` (``verdict`` ``ok`` or
``crash``, metrics per phase, disturbance recovery), ``error`` (the exception text of a run
whose verdict is ``error``), ``fasthex_version`` and ``wall_time_s``. The schema metadata key
``fasthex.sweep`` (JSON) lists the campaign, its parameters and the metric columns.

Rows stream to ``TABLE.parts/`` as small Parquet files, written atomically at most every
``flush_interval_s`` (default :data:`FLUSH_INTERVAL_S`; ``0`` writes each row as it arrives);
the table itself is rewritten from them when the sweep ends, is
interrupted (Ctrl-C, SIGTERM) or is started again. A sweep killed outright loses at most the
rows of the last interval; a rerun of the same campaign flies only the runs whose ``run_id``
is not in the table yet (``--retry-errors`` flies the ``error`` rows again; a crash is a
result, kept).

Rows are equal bit for bit whoever flies them (the flights are deterministic per seed), except
``wall_time_s`` and ``sim_s_per_wall_s`` (:data:`TIMING_COLUMNS`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import multiprocessing as mp
import os
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TextIO

from groundstation.campaign import RunSpec, execute_run
from groundstation.signals import stop_signals_blocked

if TYPE_CHECKING:
    import pyarrow as pa

#: columns that depend on the machine and its load, not on the flight
TIMING_COLUMNS = ("wall_time_s", "sim_s_per_wall_s")
IDENTITY_COLUMNS = ("run_id", "run_index", "campaign", "seed", "scenario")
TEXT_COLUMNS = ("verdict", "crash_reason", "crash_kind", "error", "fasthex_version", "mission",
                "vehicle", "preset", "estimator")
FLUSH_INTERVAL_S = 2.0
#: what a run imports (execute_run), loaded once by the forkserver the pool's workers fork from
FLIGHT_MODULES = ("groundstation.campaign", "groundstation.simulation",
                  "groundstation.session_config", "sim_backend.closed_loop", "controller.pipeline")
METADATA_KEY = b"fasthex.sweep"


# -- runners -----------------------------------------------------------------------------------

RunFunction = Callable[[RunSpec], dict[str, Any]]


class Runner(Protocol):
    """Flies runs somewhere; yields each run's row as it completes (any order)."""

    description: str

    def run(self, runs: Iterable[RunSpec]) -> Iterator[dict[str, Any]]: ...

    def close(self) -> None:
        """Stop every process the runner started; a second call does nothing."""


class SerialRunner:
    """In this process, one run after the other."""

    description = "1 worker (this process)"

    def __init__(self, fn: RunFunction = execute_run) -> None:
        self.fn = fn

    def run(self, runs: Iterable[RunSpec]) -> Iterator[dict[str, Any]]:
        for spec in runs:
            yield self.fn(spec)

    def close(self) -> None:
        pass


def _worker_main(conn: Connection, fn: RunFunction) -> None:
    """A pool worker: fly what arrives, send the row back, until told to stop (None)."""
    from groundstation.signals import ignore_stop_signals
    ignore_stop_signals()  # Ctrl-C and SIGTERM are the parent's: it ends the workers
    while True:
        try:
            spec = conn.recv()
        except (EOFError, OSError):
            return
        if spec is None:
            return
        conn.send(fn(spec))


def died_row(spec: RunSpec, reason: str) -> dict[str, Any]:
    """The row of a run whose worker died under it."""
    from groundstation.cli import version
    row: dict[str, Any] = {"run_id": spec.run_id, "run_index": spec.run_index,
                           "campaign": spec.campaign, "seed": spec.seed,
                           "scenario": spec.scenario_label, "fasthex_version": version()}
    row.update(spec.params)
    row.update(verdict="error", error=reason, wall_time_s=math.nan)
    return row


class ProcessPoolRunner:
    """``workers`` processes of our own, one run in flight per process, so that a process
    that dies is known to have died on exactly one run."""

    def __init__(self, workers: int, fn: RunFunction = execute_run) -> None:
        if workers < 1:
            raise ValueError("workers must be at least 1")
        self.workers = workers
        self.fn = fn
        self.description = f"{workers} local worker processes"
        # forkserver: a clean process (no threads of ours) that has imported the flight code
        # once; every worker, and the replacement of one that died, is a cheap fork of it
        self._ctx = mp.get_context("forkserver")
        self._ctx.set_forkserver_preload(list(FLIGHT_MODULES))
        self._procs: dict[int, tuple[Any, Connection]] = {}
        self._busy: dict[int, RunSpec] = {}  # worker -> the run it flies
        self._next_id = 0
        # The terminal sends Ctrl-C to the whole process group, `timeout` its SIGTERM too:
        # ending the workers is this process's job (close()). The forkserver and every worker
        # it forks start with the stop signals held; a worker ignores them at once, and the
        # forkserver keeps them held (it ignores only SIGINT itself).
        _start_resource_tracker()
        try:
            with stop_signals_blocked():
                while len(self._procs) < self.workers:
                    self._start()
        except BaseException:  # an interrupt the block deferred: no worker outlives it
            self.close()
            raise

    def _start(self) -> int:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_worker_main, args=(child, self.fn), daemon=True,
                                 name="fasthex-sweep-worker")
        proc.start()
        child.close()
        wid = self._next_id
        self._next_id += 1
        self._procs[wid] = (proc, parent)
        return wid

    def run(self, runs: Iterable[RunSpec]) -> Iterator[dict[str, Any]]:
        pending = iter(runs)
        busy = self._busy
        idle = [wid for wid in self._procs if wid not in busy]  # a pool is reused across run()
        while len(self._procs) < self.workers:
            idle.append(self._start())
        exhausted = False
        while True:
            while idle and not exhausted:
                spec = next(pending, None)
                if spec is None:
                    exhausted = True
                    break
                wid = idle.pop()
                self._procs[wid][1].send(spec)
                busy[wid] = spec
            if not busy:
                return
            by_handle: dict[Any, int] = {}
            for wid in busy:
                proc, conn = self._procs[wid]
                by_handle[conn] = wid
                by_handle[proc.sentinel] = wid
            for ready in wait(list(by_handle)):
                wid = by_handle[ready]
                if wid not in busy:
                    continue  # its pipe and its sentinel both woke us
                spec = busy.pop(wid)
                proc, conn = self._procs[wid]
                row: dict[str, Any] | None = None
                with contextlib.suppress(EOFError, OSError):
                    if ready is conn or conn.poll():  # a row, maybe just before it exited
                        row = conn.recv()
                if row is None:  # the process died (or its pipe broke) mid-run
                    proc.join(timeout=5.0)
                    row = died_row(spec, "the worker process died while flying this run "
                                   f"({_exit_text(proc.exitcode)})")
                    conn.close()
                    del self._procs[wid]
                    wid = self._start()
                idle.append(wid)
                yield row

    def close(self) -> None:
        """End every worker: an idle one is told to stop; one still flying a run (the sweep
        was interrupted, its run is dropped) is killed, since it ignores SIGINT and SIGTERM."""
        for wid, (proc, conn) in self._procs.items():
            if wid in self._busy:
                proc.kill()
                continue
            with contextlib.suppress(OSError, BrokenPipeError):
                conn.send(None)
        self._busy.clear()
        deadline = time.monotonic() + 5.0
        for proc, conn in self._procs.values():
            proc.join(timeout=max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)
            conn.close()
        self._procs.clear()


def _start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker (a child of ours) on its own, before the
    processes that need it: starting it unblocks SIGINT and SIGTERM in the calling thread
    (CPython holds them only while it spawns the tracker, which ignores them), which would
    let them through to the processes started after it in the same block. Started inside a
    block of its own, it keeps SIGHUP held."""
    from multiprocessing import resource_tracker
    with stop_signals_blocked():
        resource_tracker.ensure_running()


def _exit_text(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        import signal
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


class DaskRunner:
    """Runs on a ``distributed.Client``: a ``LocalCluster`` we start or a scheduler's URI."""

    def __init__(self, scheduler: str, workers: int, fn: RunFunction = execute_run) -> None:
        self.fn = fn
        try:
            from distributed import Client, LocalCluster
        except ImportError:  # pragma: no cover - a dependency of the package
            raise RuntimeError("dask.distributed is not installed (pip install "
                               "'dask[distributed]')") from None
        self._cluster: Any = None
        self.client: Any = None
        # Dask logs its cluster's life at INFO and its teardown's broken connections as
        # tracebacks: a sweep shows its own progress, and Dask's warnings only with -v
        self._log_levels = _dask_log_levels(logging.ERROR if scheduler == "local"
                                            else logging.WARNING)
        logging.getLogger("tornado.application").addFilter(_INTERRUPTED_SYNC_FILTER)
        try:
            if scheduler == "local":
                # the worker processes start with the stop signals held and never unblock
                # them: the terminal's Ctrl-C to the process group is this process's to
                # handle, and close() ends the cluster
                _start_resource_tracker()
                with stop_signals_blocked():
                    self._cluster = LocalCluster(
                        n_workers=workers, threads_per_worker=1, processes=True,
                        dashboard_address=None, silence_logs=logging.CRITICAL,
                        # no dashboard; its HTTP server on a free port of the loopback
                        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
                    self.client = Client(self._cluster)
                self.description = f"Dask LocalCluster, {workers} worker processes"
            else:
                self.client = Client(scheduler, timeout="20s")
                n = len(self.client.scheduler_info().get("workers", {}))
                self.description = f"Dask scheduler {scheduler}, {n} workers now"
        except BaseException:  # no scheduler there, or an interrupt the block deferred
            self.close()
            raise

    def run(self, runs: Iterable[RunSpec]) -> Iterator[dict[str, Any]]:
        from distributed import as_completed

        specs: dict[str, RunSpec] = {}
        futures = []
        for spec in runs:
            key = f"fasthex-run-{spec.campaign}-{spec.run_id}-{uuid.uuid4().hex[:8]}"
            specs[key] = spec
            futures.append(self.client.submit(self.fn, spec, key=key, pure=False))
        for future in as_completed(futures):
            spec = specs[future.key]
            try:
                row = future.result()
            except Exception as exc:  # a worker that died, or lost; the run's row says so
                row = died_row(spec, f"{type(exc).__name__} on the Dask cluster: {exc}")
            future.release()
            yield row

    def close(self) -> None:
        """Close the client (its runs are cancelled) and the cluster we started; what Dask
        logs while its connections close under cancelled runs is not shown."""
        during_close = _dask_log_levels(logging.CRITICAL + 1)
        try:
            if self.client is not None:
                with contextlib.suppress(Exception):
                    self.client.close()
            if self._cluster is not None:
                with contextlib.suppress(Exception):
                    self._cluster.close()
                self._cluster = None
        finally:
            _restore_log_levels(during_close)
            _restore_log_levels(self._log_levels)
            self._log_levels = {}
            logging.getLogger("tornado.application").removeFilter(_INTERRUPTED_SYNC_FILTER)


class _InterruptedSyncFilter(logging.Filter):
    """Drops the one traceback distributed's ``sync`` logs when Ctrl-C lands before its
    future exists: the ``cancel`` callback it schedules on the client's loop then reads an
    unassigned closure variable (``NameError`` in ``distributed/utils.py``), which tornado
    logs as "Exception in callback". The interrupt itself is handled by the sweep; every
    other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if not isinstance(exc, NameError) or exc.__traceback__ is None:
            return True
        tb = exc.__traceback__
        while tb.tb_next is not None:
            tb = tb.tb_next
        code = tb.tb_frame.f_code
        return not (code.co_name == "cancel"
                    and code.co_filename.replace("\\", "/").endswith("distributed/utils.py"))


_INTERRUPTED_SYNC_FILTER = _InterruptedSyncFilter()


def _dask_log_levels(level: int) -> dict[str, int]:
    """Raise Dask's loggers (``distributed`` and those below it with a level of their own)
    to at least ``level``, unless the user asked for INFO (``-v``); their previous levels."""
    if logging.getLogger().isEnabledFor(logging.INFO) and level <= logging.CRITICAL:
        return {}
    names = ["distributed", *(name for name, lg in logging.root.manager.loggerDict.items()
                              if name.startswith("distributed.")
                              and isinstance(lg, logging.Logger) and lg.level)]
    previous = {}
    for name in names:
        logger = logging.getLogger(name)
        previous[name] = logger.level
        logger.setLevel(max(level, logger.level))
    return previous


def _restore_log_levels(levels: dict[str, int]) -> None:
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)


def check_scheduler(scheduler: str) -> str:
    """``scheduler`` if it is one of the documented forms, ``local`` or ``tcp://HOST:PORT``
    (port 1 .. 65535); a one-line ``ValueError`` saying what is wrong otherwise (Dask would fail
    with a traceback, or wait its connect timeout for a port that cannot exist)."""
    from urllib.parse import urlsplit

    if scheduler == "local":
        return scheduler
    why = ""
    try:
        parts = urlsplit(scheduler)
        port = parts.port
        ok = (parts.scheme == "tcp" and bool(parts.hostname) and port is not None
              and not (parts.path or parts.query or parts.fragment))
        if ok and port == 0:
            ok, why = False, "; the port must be 1 .. 65535"
    except ValueError as exc:  # a port out of range or not a number, a bad IPv6 host
        ok = False
        why = ("; the port must be 1 .. 65535" if str(exc).startswith("Port")
               else f" ({exc})")
    if not ok:
        raise ValueError(f"--scheduler {scheduler!r}: expected 'local' or tcp://HOST:PORT{why}")
    return scheduler


#: the most local worker processes per core a sweep starts (runs are CPU-bound: more only
#: share the cores, in memory and start-up time)
MAX_WORKERS_PER_CPU = 4


def local_workers(requested: int | None, runs_left: int) -> tuple[int, str]:
    """Worker processes for a local sweep (the pool or ``--scheduler local``) and a note for
    the user if ``--workers`` (``requested``) was capped: at most one per run left to fly
    (at least 1) and :data:`MAX_WORKERS_PER_CPU` per core. The default (every core) is capped
    at the runs left without a note."""
    cpus = os.cpu_count() or 1
    n = requested if requested is not None else cpus
    limit, why = max(runs_left, 1), f"the {runs_left} run(s) to fly"
    if MAX_WORKERS_PER_CPU * cpus < limit:
        limit, why = MAX_WORKERS_PER_CPU * cpus, f"{MAX_WORKERS_PER_CPU} per core on {cpus} core(s)"
    if n <= limit:
        return n, ""
    return limit, (f" (--workers {requested} capped at {why})" if requested is not None
                   else "")


def make_runner(workers: int | None, scheduler: str | None,
                fn: RunFunction = execute_run, *, in_process: bool | None = None) -> Runner:
    """The runner for ``--workers`` / ``--scheduler`` (module docstring). ``fn`` flies one
    run (tests put a run that kills its worker in its place). ``in_process`` (default: one
    worker) flies in this process; else one worker is a pool of one, which a crash cannot end
    (``--workers 8`` capped at the one run left to fly)."""
    n = workers if workers is not None else (os.cpu_count() or 1)
    if scheduler is not None:
        return DaskRunner(check_scheduler(scheduler), n, fn)
    if n == 1 if in_process is None else in_process:
        return SerialRunner(fn)
    return ProcessPoolRunner(n, fn)


# -- the table ---------------------------------------------------------------------------------

def _column_type(values: list[Any]) -> pa.DataType:
    import pyarrow as pa
    present = [v for v in values if v is not None]
    if not present:
        return pa.float64()
    if all(isinstance(v, bool) for v in present):
        return pa.bool_()
    if all(isinstance(v, int) and not isinstance(v, bool) for v in present):
        return pa.int64()
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in present):
        return pa.float64()
    return pa.string()


def _cell(value: Any, tp: pa.DataType) -> Any:
    import pyarrow as pa
    if value is None:
        return None
    if tp == pa.string():
        return value if isinstance(value, str) else json.dumps(value)
    if tp == pa.float64():
        return float(value)
    return value


def rows_to_table(rows: list[dict[str, Any]], meta: dict[str, Any]) -> pa.Table:
    """A tidy Arrow table of rows with possibly different keys (missing cells null/NaN)."""
    import pyarrow as pa
    params: list[str] = list(meta.get("parameters", []))
    columns: list[str] = []
    seen: set[str] = set()
    for name in (*IDENTITY_COLUMNS, *params, "verdict", "crash_reason", "error"):
        if name not in seen:
            columns.append(name)
            seen.add(name)
    for row in rows:
        for name in row:
            if name not in seen:
                columns.append(name)
                seen.add(name)
    fields, arrays = [], []
    metrics: list[str] = []
    for name in columns:
        values = [row.get(name) for row in rows]
        tp = pa.string() if name in TEXT_COLUMNS else _column_type(values)
        if name == "scenario":
            tp = pa.string()
        if tp == pa.float64():
            values = [math.nan if v is None else v for v in values]
            if name not in params and name not in IDENTITY_COLUMNS:
                metrics.append(name)
        fields.append(pa.field(name, tp))
        arrays.append(pa.array([_cell(v, tp) for v in values], type=tp))
    full_meta = dict(meta, metrics=metrics, version=1)
    schema = pa.schema(fields, metadata={METADATA_KEY: json.dumps(full_meta).encode()})
    return pa.Table.from_arrays(arrays, schema=schema)


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of one Parquet file, NaN metrics as None again (so they merge by key)."""
    import pyarrow.parquet as pq
    table = pq.read_table(path)
    out = []
    for row in table.to_pylist():
        out.append({k: (None if isinstance(v, float) and math.isnan(v) else v)
                    for k, v in row.items()})
    return out


def read_metadata(path: Path) -> dict[str, Any]:
    import pyarrow.parquet as pq
    raw = (pq.read_schema(path).metadata or {}).get(METADATA_KEY)
    return {} if raw is None else dict(json.loads(raw))


def write_durably(table: pa.Table, path: Path) -> None:
    """Write ``table`` to ``path`` through ``PATH.tmp``, fsync'ed before the atomic rename and
    the folder after it: a power loss leaves the old file or the whole new one, never a
    truncated one under the final name."""
    import pyarrow.parquet as pq
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        pq.write_table(table, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class ResultsTable:
    """The sweep's Parquet table and its journal of parts (module docstring).

    A part that cannot be read (cut short by a crash of the machine before part files were
    fsync'ed, or by a disk) is renamed ``PART.corrupt`` (with ``set_aside``; else only skipped)
    and listed in :attr:`unreadable`: its runs are not in the table, so they fly again."""

    def __init__(self, path: Path, meta: dict[str, Any], *,
                 flush_interval_s: float = FLUSH_INTERVAL_S, set_aside: bool = True) -> None:
        if not flush_interval_s >= 0.0:  # also refuses NaN
            raise ValueError(f"flush interval must be >= 0 s, got {flush_interval_s}")
        self.path = path
        self.flush_interval_s = flush_interval_s
        self.parts_dir = path.with_name(path.name + ".parts")
        self.meta = meta
        self._buffer: list[dict[str, Any]] = []
        self._last_flush = time.monotonic()
        self._part = 0
        self.rows: dict[str, dict[str, Any]] = {}
        #: the unreadable parts: (their path now, why)
        self.unreadable: list[tuple[Path, str]] = []
        if path.exists():
            for row in read_rows(path):
                self.rows[str(row["run_id"])] = row
        if self.parts_dir.is_dir():
            for part in sorted(self.parts_dir.glob("part-*.parquet")):
                try:
                    rows = read_rows(part)
                except (OSError, ValueError) as exc:  # pyarrow's ArrowInvalid: a ValueError
                    if set_aside:
                        part = part.rename(part.with_name(part.name + ".corrupt"))
                    self.unreadable.append((part, str(exc)))
                    continue
                for row in rows:
                    self.rows[str(row["run_id"])] = row

    def done_ids(self, *, retry_errors: bool = False) -> set[str]:
        return {rid for rid, row in self.rows.items()
                if not (retry_errors and row.get("verdict") == "error")}

    def add(self, row: dict[str, Any]) -> None:
        self.rows[str(row["run_id"])] = row
        self._buffer.append(row)
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Write the buffered rows as one part file (atomically, fsync'ed)."""
        self._last_flush = time.monotonic()
        if not self._buffer:
            return
        self.parts_dir.mkdir(parents=True, exist_ok=True)
        name = f"part-{time.time_ns():020d}-{os.getpid()}-{self._part:05d}.parquet"
        self._part += 1
        write_durably(rows_to_table(self._buffer, self.meta), self.parts_dir / name)
        self._buffer = []

    def consolidate(self) -> None:
        """Rewrite the table from every row known (table + parts), ordered by run index, then
        drop the parts (a ``.corrupt`` one stays, for a look). Atomic: the old table stays
        whole until the new one replaces it."""
        self.flush()
        rows = sorted(self.rows.values(), key=lambda r: (r.get("run_index") or 0,
                                                         str(r["run_id"])))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_durably(rows_to_table(rows, self.meta), self.path)
        if self.parts_dir.is_dir():
            for pattern in ("part-*.parquet", "part-*.parquet.tmp"):
                for part in self.parts_dir.glob(pattern):
                    part.unlink()
            with contextlib.suppress(OSError):
                self.parts_dir.rmdir()


# -- progress ----------------------------------------------------------------------------------

class Progress:
    """A progress line with rate and ETA: rewritten in place on a terminal, a line every 10 %
    (or 30 s) otherwise."""

    def __init__(self, total: int, stream: TextIO | None = None, label: str = "sweep") -> None:
        self.total, self.done, self.failed = total, 0, 0
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.label = label
        self.t0 = time.monotonic()
        self._last_print = -math.inf
        self._last_decile = -1
        self._line_open = False  # a line drawn on the terminal, not ended yet

    def update(self, row: dict[str, Any]) -> None:
        self.done += 1
        if row.get("verdict") != "ok":
            self.failed += 1
        now = time.monotonic()
        decile = (10 * self.done) // max(self.total, 1)
        if self.tty or decile != self._last_decile or now - self._last_print >= 30.0 \
                or self.done == self.total:
            self._last_decile = decile
            self._last_print = now
            self._write(self.line(now))

    def line(self, now: float | None = None) -> str:
        now = time.monotonic() if now is None else now
        elapsed = now - self.t0
        rate_per_min = 60.0 * self.done / elapsed if elapsed > 0 else 0.0
        left = self.total - self.done
        eta = left * elapsed / self.done if self.done else math.nan
        pct = 100.0 * self.done / self.total if self.total else 100.0
        width = 24
        filled = int(width * self.done / self.total) if self.total else width
        bar = "#" * filled + "." * (width - filled)
        return (f"{self.label} [{bar}] {self.done}/{self.total} runs ({pct:.0f} %), "
                f"{self.failed} not ok, {rate_per_min:.1f} runs/min, elapsed "
                f"{_hms(elapsed)}, ETA {_hms(eta)}")

    def _write(self, text: str) -> None:
        # a terminal that went away (SIGHUP) does not stop the sweep, nor its clean end
        with contextlib.suppress(OSError):
            if self.tty:
                # open before the write: a Ctrl-C between the two must still end the line
                self._line_open = True
                self.stream.write("\r\x1b[2K" + text)
            else:
                self.stream.write(text + "\n")
            self.stream.flush()

    def finish(self) -> None:
        """End the line drawn on the terminal (what is printed next starts a line)."""
        if self._line_open:
            self._line_open = False
            with contextlib.suppress(OSError):
                self.stream.write("\n")
                self.stream.flush()


def _hms(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "--:--"
    s = round(seconds)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else \
        f"{s // 60}:{s % 60:02d}"


# -- the sweep ---------------------------------------------------------------------------------

def sweep(runs: list[RunSpec], table: ResultsTable, runner: Runner, *,
          retry_errors: bool = False, progress: Progress | None = None,
          on_row: Callable[[dict[str, Any]], None] | None = None) -> tuple[int, int]:
    """Fly every run not in the table yet; returns (runs flown now, runs already there).

    The table is consolidated on the way out, also when interrupted."""
    done = table.done_ids(retry_errors=retry_errors)
    todo = [r for r in runs if r.run_id not in done]
    skipped = len(runs) - len(todo)
    flown = 0
    try:
        for row in runner.run(todo):
            table.add(row)
            flown += 1
            if progress is not None:
                progress.update(row)
            if on_row is not None:
                on_row(row)
    finally:
        try:
            if progress is not None:
                progress.finish()
            runner.close()
        finally:  # the rows are saved even if a second Ctrl-C cuts the runner's close short
            table.consolidate()
    return flown, skipped
