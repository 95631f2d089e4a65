"""Layering: nothing under drivers/ imports the ground station (the MAVLink bridge, which
knows flight phases and operator commands, lives in groundstation/)."""

from __future__ import annotations

import ast
from pathlib import Path

import drivers

DRIVERS = Path(drivers.__file__).parent


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_that_no_driver_module_imports_the_groundstation_package() -> None:
    offenders = {str(p.relative_to(DRIVERS)): sorted(m for m in _imports(p)
                                                     if m.split(".")[0] == "groundstation")
                 for p in DRIVERS.rglob("*.py")}
    assert {k: v for k, v in offenders.items() if v} == {}
    assert (DRIVERS / "mavlink" / "signing.py").exists()  # the scan did see the MAVLink layer


def test_that_the_mavlink_driver_package_loads_without_the_groundstation_in_a_fresh_process(
        ) -> None:
    import subprocess
    import sys

    code = ("import sys, drivers.mavlink, drivers.mavlink.link, drivers.mavlink.mocap; "
            "print(sorted(m for m in sys.modules if m.startswith('groundstation')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60)
    assert out.stdout.strip() == "[]"
