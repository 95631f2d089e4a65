"""Mutation testing of the safety code: one-line changes, each run against the tests that should
notice it. Run by hand (it is slow, not part of CI)::

    python tools/mutation.py                      # every target, fast unit tests only
    python tools/mutation.py --targets flight signing --list
    python tools/mutation.py --targets loop --max-mutants 40 --timeout 600

A small AST mutator of its own (mutmut works on a ``mutants/`` copy inside the project and
rewrites files it is pointed at; here the project tree is never touched): the repository's
sources are copied to a temporary directory once, and each mutant is written into that copy
only, then the target's tests run there (``PYTHONPATH`` points at the copy, so the emulator and
the telemetry processes the flight tests start import the mutant too).

Operators: comparisons flipped at their boundary (``<`` / ``<=``, ``>`` / ``>=``) and negated
(``==`` / ``!=``, ``is`` / ``is not``, ``in`` / ``not in``), ``and`` / ``or`` swapped, ``not``
dropped, an ``if``/``while`` condition negated, integer constants off by one, float constants
scaled by 2.5, ``+`` / ``-`` swapped, ``return X`` replaced by ``return None`` (or the opposite
boolean). A mutant is *killed* when a test fails (or the module no longer imports), *survived*
when every selected test passes, *timeout* when the tests exceed ``--timeout``.

Prints one line per mutant and, at the end, killed / survived / timeout and the score, with
each survivor's file, line and change.
"""

from __future__ import annotations

import argparse
import ast
import copy
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COPY_DIRS = ("config", "controller", "drivers", "estimator", "groundstation", "sim_backend",
             "tests", "tools")
COPY_FILES = ("pyproject.toml",)


@dataclass(frozen=True)
class Target:
    """A source file, which of its functions to mutate (qualified names; empty: all), an
    optional filter on the statements inside them, and the tests that should notice."""

    name: str
    path: str
    functions: tuple[str, ...]
    tests: tuple[str, ...]
    #: only statements whose source mentions one of these names (empty: every statement)
    mentions: tuple[str, ...] = ()
    #: the tests need no fixture of tests/conftest.py (pytest starts 2-3x faster without it)
    noconftest: bool = False


TARGETS = (
    Target("flight", "groundstation/flight.py", (),
           ("tests/unit/test_flight_state_machine.py",), noconftest=True),
    Target("preflight", "groundstation/loop.py",
           ("FlightLoop._preflight", "FlightLoop._health", "_servo_health"),
           ("tests/unit/test_preflight_checks.py",
            "tests/integration/test_failsafes.py::"
            "test_that_a_silent_servo_a_slow_imu_and_a_displaced_vehicle_each_refuse_the_flight",
            "tests/integration/test_failsafes.py::"
            "test_that_no_mocap_refuses_the_flight_and_no_check_passes_on_the_placeholder_estimate",
            "tests/integration/test_failsafes.py::"
            "test_that_body_tilt_just_over_its_limit_lands_at_the_first_tick_over_it")),
    Target("loop", "groundstation/loop.py", ("FlightLoop.run",),
           ("tests/integration/test_failsafes.py",
            "tests/integration/test_takeoff_on_estimate.py",
            # the realtime branches (pose age on the host clock, RATE_LOW from the driver)
            "tests/integration/test_clock_sync.py::"
            "test_the_preflight_reports_the_board_and_mocap_clocks"),
           mentions=("link_ok", "battery_v", "estimator_ok", "imu_rate_fraction", "rate_seq0",
                     "rate_n0", "last_pose_t_s", "pose_age_s", "passed", "timed_out",
                     "n_transitions")),
    Target("record", "groundstation/record.py",
           ("RecordWriter.append", "RecordWriter.append_block", "RecordWriter.flush",
            "RecordWriter._write_block", "RecordWriter.close", "parse_record"),
           ("tests/unit/test_simulator_record.py", "tests/unit/test_report.py",
            "tests/unit/test_safety_boundaries.py", "tests/integration/test_fly_kill.py")),
    Target("telemetry", "groundstation/session.py", ("_telemetry_main",),
           ("tests/integration/test_fly_kill.py",)),
    Target("signing", "drivers/mavlink/signing.py", (),
           ("tests/unit/test_mavlink_signing.py", "tests/unit/test_safety_boundaries.py"),
           noconftest=True),
    Target("operator", "groundstation/operator.py", ("decide",),
           ("tests/unit/test_mavlink_operator.py", "tests/unit/test_mavlink_gcs.py",
            "tests/unit/test_safety_boundaries.py"),
           noconftest=True),
)


@dataclass(frozen=True)
class Mutant:
    target: Target
    line: int
    description: str
    source: str


# -- the mutator ---------------------------------------------------------------------------------
_CMP_SWAP: dict[type[ast.cmpop], type[ast.cmpop]] = {
    ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq,
    ast.NotEq: ast.Eq, ast.Is: ast.IsNot, ast.IsNot: ast.Is, ast.In: ast.NotIn,
    ast.NotIn: ast.In,
}
_SYMBOL = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!=",
           ast.Is: "is", ast.IsNot: "is not", ast.In: "in", ast.NotIn: "not in"}


def _mutations(node: ast.AST) -> Iterator[tuple[str, Callable[[ast.AST], None]]]:
    """(description, apply) for each mutation of this one node (apply edits a copy)."""
    if isinstance(node, ast.Compare):
        for i, op in enumerate(node.ops):
            swapped = _CMP_SWAP.get(type(op))
            if swapped is not None:
                def flip(n: ast.AST, i: int = i, swapped: type[ast.cmpop] = swapped) -> None:
                    assert isinstance(n, ast.Compare)
                    n.ops[i] = swapped()
                yield f"{_SYMBOL[type(op)]} -> {_SYMBOL[swapped]}", flip
    elif isinstance(node, ast.BoolOp):
        def swap(n: ast.AST) -> None:
            assert isinstance(n, ast.BoolOp)
            n.op = ast.Or() if isinstance(n.op, ast.And) else ast.And()
        yield ("and -> or" if isinstance(node.op, ast.And) else "or -> and"), swap
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
        yield "not x -> x", lambda n: None  # handled by the parent replacement below
    elif isinstance(node, ast.Constant) and type(node.value) in (int, float) \
            and not isinstance(node.value, bool):
        value = node.value
        if isinstance(value, int):
            def plus(n: ast.AST) -> None:
                assert isinstance(n, ast.Constant)
                n.value = value + 1
            yield f"{value} -> {value + 1}", plus
        elif isinstance(value, float) and value != 0.0:
            scaled = value * 2.5

            def scale(n: ast.AST) -> None:
                assert isinstance(n, ast.Constant)
                n.value = scaled
            yield f"{value!r} -> {scaled!r}", scale
    elif isinstance(node, ast.Constant) and isinstance(node.value, bool):
        def flip_bool(n: ast.AST) -> None:
            assert isinstance(n, ast.Constant)
            n.value = not n.value
        yield f"{node.value} -> {not node.value}", flip_bool
    elif isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub)):
        def arith(n: ast.AST) -> None:
            assert isinstance(n, ast.BinOp)
            n.op = ast.Sub() if isinstance(n.op, ast.Add) else ast.Add()
        yield ("+ -> -" if isinstance(node.op, ast.Add) else "- -> +"), arith
    elif isinstance(node, (ast.If, ast.While)):
        def negate(n: ast.AST) -> None:
            assert isinstance(n, (ast.If, ast.While))
            n.test = ast.UnaryOp(op=ast.Not(), operand=n.test)
        yield f"{'if' if isinstance(node, ast.If) else 'while'} condition negated", negate
    elif isinstance(node, ast.Return) and node.value is not None:
        v = node.value
        if isinstance(v, ast.Constant) and isinstance(v.value, bool):
            return  # the bool flip covers it
        def ret_none(n: ast.AST) -> None:
            assert isinstance(n, ast.Return)
            n.value = ast.Constant(value=None)
        yield "return X -> return None", ret_none


class _DropNot(ast.NodeTransformer):
    """Replaces one ``not x`` (by identity) with ``x``."""

    def __init__(self, target: ast.AST) -> None:
        self.target = target

    def visit_UnaryOp(self, node: ast.UnaryOp) -> ast.AST:
        if node is self.target:
            return node.operand
        return self.generic_visit(node)


def _functions(tree: ast.Module, names: tuple[str, ...]) -> list[ast.AST]:
    if not names:
        return [tree]
    found: list[ast.AST] = []
    seen: set[str] = set()

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                qual = f"{prefix}{child.name}"
                if qual in names and not isinstance(child, ast.ClassDef):
                    found.append(child)
                    seen.add(qual)
                walk(child, qual + ".")
    walk(tree, "")
    missing = set(names) - seen
    if missing:
        raise SystemExit(f"mutation: no function {sorted(missing)} in the target")
    return found


def mutants_of(target: Target, root: Path = ROOT) -> list[Mutant]:
    text = (root / target.path).read_text()
    tree = ast.parse(text)
    lines = text.splitlines()
    scopes = _functions(tree, target.functions)
    candidates: list[ast.AST] = []
    for scope in scopes:
        for node in ast.walk(scope):
            if node is scope:
                continue
            candidates.append(node)
    if target.mentions:
        keep: set[int] = set()
        for scope in scopes:
            for stmt in ast.walk(scope):
                if isinstance(stmt, ast.stmt) and stmt is not scope and not isinstance(
                        stmt, (ast.While, ast.For, ast.FunctionDef, ast.Try)):
                    seg = ast.get_source_segment(text, stmt) or ""
                    head = seg.splitlines()[0] if isinstance(stmt, ast.If) else seg
                    if any(m in head for m in target.mentions):
                        for sub in ast.walk(stmt):
                            if isinstance(stmt, ast.If) and sub in stmt.body + stmt.orelse:
                                break
                            keep.add(id(sub))
        candidates = [c for c in candidates if id(c) in keep]
    out: list[Mutant] = []
    seen: set[str] = set()
    for node in candidates:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            continue
        if not hasattr(node, "lineno"):
            continue
        for desc, apply in _mutations(node):
            index = _index_of(tree, node)
            mutated = copy.deepcopy(tree)
            twin = _node_at(mutated, index)
            if isinstance(twin, ast.UnaryOp) and isinstance(twin.op, ast.Not):
                mutated = _DropNot(twin).visit(mutated)
            else:
                apply(twin)
            ast.fix_missing_locations(mutated)
            try:
                source = ast.unparse(mutated)
            except Exception:  # an operator that made no valid tree
                continue
            if source in seen:
                continue
            seen.add(source)
            line = node.lineno
            code = lines[line - 1].strip() if 0 < line <= len(lines) else ""
            out.append(Mutant(target, line, f"{desc}  [{code[:70]}]", source))
    return out


def _index_of(tree: ast.AST, node: ast.AST) -> int:
    for i, n in enumerate(ast.walk(tree)):
        if n is node:
            return i
    raise ValueError("node not in tree")


def _node_at(tree: ast.AST, index: int) -> ast.AST:
    for i, n in enumerate(ast.walk(tree)):
        if i == index:
            return n
    raise IndexError(index)


# -- running -------------------------------------------------------------------------------------
def make_copy(root: Path = ROOT) -> Path:
    work = Path(tempfile.mkdtemp(prefix="fasthex-mutation-"))
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".pytest_cache", "*.fhr", "*.rrd")
    for d in COPY_DIRS:
        if (root / d).exists():
            shutil.copytree(root / d, work / d, ignore=ignore)
    for f in COPY_FILES:
        shutil.copy2(root / f, work / f)
    return work


def run_tests(work: Path, tests: tuple[str, ...], timeout_s: float,
              noconftest: bool = False) -> tuple[str, float]:
    env = dict(os.environ, PYTHONPATH=str(work), PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
           "--no-header", "-o", "addopts=--import-mode=importlib",
           *(["--noconftest"] if noconftest else []), *tests]
    t0 = time.monotonic()
    try:
        proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True,
                              timeout=timeout_s, start_new_session=True)
    except subprocess.TimeoutExpired:
        return "timeout", time.monotonic() - t0
    dt = time.monotonic() - t0
    if proc.returncode == 0:
        return "survived", dt
    if proc.returncode == 5:  # nothing collected: a broken selection, not a kill
        raise SystemExit(f"mutation: no tests collected for {tests}")
    run_tests.last_output = proc.stdout[-3000:]  # type: ignore[attr-defined]
    return "killed", dt


def _select(mutants: list[Mutant], skip: int, lines: str) -> list[Mutant]:
    wanted: set[int] = set()
    for part in filter(None, lines.split(",")):
        lo, _, hi = part.partition("-")
        wanted.update(range(int(lo), int(hi or lo) + 1))
    return [m for m in mutants[skip:] if not wanted or m.line in wanted]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", nargs="*", default=[t.name for t in TARGETS
                                                     if t.name not in ("loop", "telemetry")],
                    choices=[t.name for t in TARGETS],
                    help="default: every target whose tests are fast (not loop, telemetry)")
    ap.add_argument("--list", action="store_true", help="list the mutants, run nothing")
    ap.add_argument("--max-mutants", type=int, default=0, help="per target (0: all)")
    ap.add_argument("--skip", type=int, default=0, help="per target: leave out its first N "
                    "mutants (the order is deterministic: resume an interrupted run)")
    ap.add_argument("--lines", default="", help="only mutants on these source lines, "
                    "e.g. 720-724,393")
    ap.add_argument("--timeout", type=float, default=300.0, help="per mutant, seconds")
    ap.add_argument("--tests", nargs="*", default=None,
                    help="override the target's tests (pytest node ids)")
    ap.add_argument("--rev", default=None, help="mutate the targets as committed in this git "
                    "revision (e.g. HEAD), not as they are in the working tree")
    ap.add_argument("--jobs", type=int, default=1, help="mutants run side by side (each in "
                    "a copy of its own)")
    args = ap.parse_args(argv)
    targets = [t for t in TARGETS if t.name in args.targets]
    if args.list:
        for target in targets:
            mutants = _select(mutants_of(target), args.skip, args.lines)
            print(f"== {target.name}: {target.path} ({len(mutants)} mutants)")
            for m in mutants:
                print(f"  {m.target.path}:{m.line}: {m.description}")
        return 0
    works = [make_copy() for _ in range(max(1, args.jobs))]
    if args.rev:  # the committed sources of the targets (others' edits in progress left out)
        for target in targets:
            text = subprocess.run(["git", "show", f"{args.rev}:{target.path}"], cwd=ROOT,
                                  capture_output=True, text=True, check=True).stdout
            for w in works:
                (w / target.path).write_text(text)
    totals = {"killed": 0, "survived": 0, "timeout": 0}
    survivors: list[Mutant] = []
    try:
        for target in targets:
            mutants = _select(mutants_of(target, works[0]), args.skip, args.lines)
            if args.max_mutants:
                mutants = mutants[:args.max_mutants]
            print(f"== {target.name}: {target.path} ({len(mutants)} mutants)", flush=True)
            tests = tuple(args.tests) if args.tests else target.tests
            verdict, dt = run_tests(works[0], tests, args.timeout, target.noconftest)
            if verdict != "survived":
                raise SystemExit(f"mutation: the unmutated tests of {target.name} do not pass "
                                 f"({verdict}); fix them first\n"
                                 f"{getattr(run_tests, 'last_output', '')}")
            print(f"  baseline passes in {dt:.1f} s", flush=True)
            original = (works[0] / target.path).read_text()
            free: queue.Queue[Path] = queue.Queue()
            for w in works:
                free.put(w)

            def one(m: Mutant, tests: tuple[str, ...] = tests, target: Target = target,
                    free: queue.Queue[Path] = free, original: str = original
                    ) -> tuple[Mutant, str, float]:
                work = free.get()
                try:
                    (work / target.path).write_text(m.source)
                    verdict, dt = run_tests(work, tests, args.timeout, target.noconftest)
                finally:
                    (work / target.path).write_text(original)
                    free.put(work)
                return m, verdict, dt

            with ThreadPoolExecutor(max_workers=len(works)) as pool:
                for m, verdict, dt in pool.map(one, mutants):
                    totals[verdict] += 1
                    if verdict == "survived":
                        survivors.append(m)
                    print(f"  {verdict:8s} {dt:6.1f} s  {m.target.path}:{m.line}: "
                          f"{m.description}", flush=True)
    finally:
        for w in works:
            shutil.rmtree(w, ignore_errors=True)
    n = sum(totals.values())
    score = 100.0 * totals["killed"] / n if n else 0.0
    print(f"\nkilled {totals['killed']}, survived {totals['survived']}, timeout "
          f"{totals['timeout']} of {n}: {score:.1f} % killed")
    for m in survivors:
        print(f"  survived: {m.target.path}:{m.line}: {m.description}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
