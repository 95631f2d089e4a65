"""Entry points of child processes started by tests ("spawn" imports them by module name, so
they live in this module on the tests' path, not inside a test module)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np


def hammer_mailbox(mailbox: Any, count: int, done: Any) -> None:
    """Publish ``count`` servo states whose slots all hold the same number."""
    from drivers.dynamixel.device import _S

    values = [0.0] * int(_S.N)
    for i in range(1, count + 1):
        values[1:] = [float(i)] * (int(_S.N) - 1)
        mailbox.publish(values)
    done.set()


def read_ring(name: str, n_cols: int, expected: int, out: Any) -> None:
    """Drain a float telemetry ring until ``expected`` rows arrived (or 60 s)."""
    from groundstation.telemetry import TelemetryRing

    ring = TelemetryRing((np.float64, n_cols), capacity=64, name=name)
    got: list[np.ndarray] = []
    deadline = time.monotonic() + 60.0
    while sum(len(g) for g in got) < expected and time.monotonic() < deadline:
        rows = ring.drain()
        if len(rows):
            got.append(rows)
        else:
            time.sleep(0.001)
    ring.close()
    out.put(np.concatenate(got) if got else np.empty((0, n_cols)))


def run_or_die(spec: Any) -> dict[str, Any]:
    """A campaign run that kills its worker process when its seed is 13 (a segfault, the OOM
    killer), else the real run."""
    import os

    from groundstation.campaign import execute_run

    if spec.seed == 13:
        os._exit(9)
    return execute_run(spec)


# ---- integration/test_fly_kill.py: a realtime flight in a process group of its own

START_Z_M, TAKEOFF_HEIGHT_M = 0.1, 0.8
MISSION = f"""\
schema: fasthex.mission
version: 1
name: long-hover
description: take off and hover for a minute
start_pos_w_m: [0.1, -0.1, {START_Z_M}]
segments:
  - kind: takeoff
    duration_s: 2.5
    height_m: {TAKEOFF_HEIGHT_M}
    alpha: {{kind: constant, value_deg: 0.0}}
  - kind: hold
    duration_s: 60.0
  - kind: land
    duration_s: 4.0
    alpha: {{kind: constant, value_deg: 0.0}}
"""
SESSION = """\
schema: fasthex.session
version: 1
name: long-hover-realtime
vehicle: fasthex
mission: long-hover.yaml
backend:
  kind: emulated
  clock: realtime
  seed: 3
  disturbances: paper-calibrated
safety:
  geofence_min_m: [-2.0, -2.0, -0.5]
  geofence_max_m: [2.0, 2.0, 2.5]
  imu_timeout_s: 0.1
  failsafe_action: land
telemetry:
  rerun: "off"
"""


def fly_long_hover_in_own_group(tmp: str) -> None:
    """Child-process entry: a process group of its own (the ground station and the telemetry
    and servo processes it starts), devices linked in ``tmp/dev``, where the emulator leaves
    its truth log and its exit note."""
    import os
    from pathlib import Path

    import groundstation.session as session_module
    from controller.missions import Mission
    from groundstation.configs import load_mission, load_vehicle
    from groundstation.session import FlightSession
    from groundstation.session_config import load_session

    os.setpgid(0, 0)

    class EmulatorWithTruth(session_module.EmulatorProcess):
        """The real emulator, with its truth log on: a realtime session leaves it off (its
        writes come from the board's thread); the measurement needs it."""

        def __init__(self, cfg: Any, vehicle: str, start: Any, link_dir: Path, *args: Any,
                     **kwargs: Any) -> None:
            kwargs.pop("truth_path", None)
            rest = list(args)
            rest[1:2] = [link_dir / "truth.f64"]
            super().__init__(cfg, vehicle, start, link_dir, *rest, **kwargs)

    session_module.EmulatorProcess = EmulatorWithTruth  # type: ignore[misc,assignment]
    tmp_path = Path(tmp)
    (tmp_path / "long-hover.yaml").write_text(MISSION)
    (tmp_path / "session.yaml").write_text(SESSION)
    dev = tmp_path / "dev"
    dev.mkdir(exist_ok=True)
    FlightSession(load_session(tmp_path / "session.yaml"), load_vehicle("fasthex"),
                  Mission(load_mission(tmp_path / "long-hover.yaml")),
                  record_path=tmp_path / "killed.fhr", session_dir=dev,
                  echo_events=False).run()


def wait_on_flag_for_ever(flag: Any, ready: Any) -> None:
    """Say so on ``ready``, then wait on ``flag`` with no time limit (to be killed there)."""
    ready.set()
    flag.wait()


def set_flag_after_its_waiter_died(kind: str, conn: Any) -> None:
    """In a process of its own (it may hang): a waiter asleep in ``flag.wait()`` is killed,
    then the flag is set; says on ``conn`` when the waiter is dead and when ``set()`` returned.
    ``kind``: "flag" (drivers.shared_flag.SharedFlag) or "event" (multiprocessing.Event)."""
    import multiprocessing as mp
    import os
    import signal

    from drivers.shared_flag import SharedFlag

    ctx = mp.get_context("spawn")
    flag: Any = SharedFlag(ctx) if kind == "flag" else ctx.Event()
    ready = SharedFlag(ctx)
    waiter = ctx.Process(target=wait_on_flag_for_ever, args=(flag, ready), daemon=True)
    waiter.start()
    assert ready.wait(60.0)
    time.sleep(0.3)  # asleep in its wait by now
    os.kill(waiter.pid, signal.SIGKILL)  # type: ignore[arg-type]
    waiter.join()
    conn.send("dead")
    flag.set()
    conn.send("set")


def set_flag_later(flag: Any, delay_s: float) -> None:
    time.sleep(delay_s)
    flag.set()
