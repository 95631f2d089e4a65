"""Every config of the generated malformed corpus (``tools/config_corpus.py``) is refused by the
real command line, in this process: exit 2 and exactly one ``fasthex: config error:
FILE:LINE: KEY: expectation`` line (``FILE:LINE: expectation`` for reader-level errors) naming
the file at fault, no traceback, and no flight started: validation comes before any emulator."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from collections import Counter
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from config import config_root
from groundstation.cli import main

TOOL = Path(__file__).resolve().parents[2] / "tools" / "config_corpus.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("config_corpus", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["config_corpus"] = module  # dataclasses resolve their module by name
    spec.loader.exec_module(module)
    return module


CORPUS = _tool()


@pytest.fixture(scope="module")
def cases(tmp_path_factory: pytest.TempPathFactory) -> list[Any]:
    shipped_before = sorted(config_root().rglob("*.yaml"))
    out = tmp_path_factory.mktemp("corpus")
    generated = list(CORPUS.generate(out))
    # the generator writes only into its folder, never next to the shipped files
    assert sorted(config_root().rglob("*.yaml")) == shipped_before
    assert all(Path(c.file).is_relative_to(out) or Path(c.file).is_relative_to(config_root())
               for c in generated)
    return generated


def test_that_the_corpus_covers_all_four_kinds_and_every_mutation_family(
        cases: list[Any]) -> None:
    kinds = Counter(c.kind for c in cases)
    names = " | ".join(c.name for c in cases)
    assert len(cases) >= 300
    assert set(kinds) == set(CORPUS.KINDS) and min(kinds.values()) >= 50
    for family in ("= abc", "= .nan", "= -.inf", "= 1e9", "(absurd)", "(literal)",
                   "unknown key", "duplicate key", "missing ", "NUL byte", "invalid UTF-8",
                   "tab indentation", "deep nesting", "huge file", "billion laughs",
                   "two documents", "empty file", "vehicle reference", "mission reference",
                   "disturbances reference", "outside the geofence", "beyond 35 deg",
                   "fixed-tilt", "takeoff to 0.1 m", "MoCap at"):
        assert family in names, family


def test_that_every_malformed_config_gives_exit_2_and_one_located_line(
        cases: list[Any], capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a flight refuses to start (no emulator, no ports) if validation lets one by
    failures: list[str] = []
    with CORPUS.no_flights():
        for case in cases:
            # Test
            try:
                code = main(list(case.argv))
            except BaseException as exc:  # a traceback is the failure looked for
                capsys.readouterr()
                failures.append(f"{case.name}: raised {type(exc).__name__}: {exc}")
                continue
            err = capsys.readouterr().err
            # Assert (collected, so that one run reports every failing case)
            problem = CORPUS.judge(case, code, err)
            if problem:
                failures.append(f"[{case.kind}] {case.name}: {problem}: {err.strip()}")
    assert not failures, f"{len(failures)} of {len(cases)} cases:\n" + "\n".join(failures[:30])


@pytest.mark.parametrize("name", ["NUL byte", "billion laughs"])
def test_that_the_installed_command_refuses_reader_garbage_without_a_traceback(
        cases: list[Any], name: str) -> None:
    # a few cases through a real process: what a user's shell sees
    case = next(c for c in cases if c.name == name and c.kind == "vehicles")
    proc = subprocess.run([sys.executable, "-m", "groundstation", *case.argv],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert CORPUS.judge(case, proc.returncode, proc.stderr) == ""
