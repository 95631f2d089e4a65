"""A lockstep simulated flight seen through the MAVLink bridge by a mavutil GCS.

The in-process closed loop (mission -> controller -> simulator, 500 Hz) flies the first 3 s of
the paper's Exp. 2b (the take-off); every tick's record row becomes a
:class:`~groundstation.operator.VehicleTelemetry` handed to the bridge, which is stepped with
the flight's own time. The GCS must see each message at its configured rate in simulated time,
with the values of the row whose time stamp it carries, converted to NED.
"""

from __future__ import annotations

import math
import os
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil

from controller.missions import Mission
from drivers.mavlink import MavlinkConfig
from drivers.mavlink.frames import q_to_euler, q_world_to_ned, world_to_ned
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.mavlink_bridge import MavlinkBridge
from groundstation.operator import (
    FlightPhase,
    RuleBasedCommandSink,
    SensorHealth,
    VehicleTelemetry,
)
from groundstation.record import RECORD_DTYPE, nested_row
from sim_backend.closed_loop import fly_mission

mavutil.set_dialect("common")
RATE_HZ = 500.0
DURATION_S = 3.0
TIMEOUT_S = 30.0
FIELDS = RECORD_DTYPE.names or ()


def _vec(v: Any) -> tuple[float, ...]:
    return tuple(float(x) for x in v)


class BridgeSink:
    """A RowSink: each record row -> snapshot -> bridge, stepped at the row's time; the GCS
    socket is drained every tick so nothing piles up in its receive buffer."""

    def __init__(self, bridge: MavlinkBridge, gcs: Any) -> None:
        self.bridge = bridge
        self.gcs = gcs
        self.rows: dict[int, dict[str, Any]] = {}
        self.received: list[Any] = []

    def append_flat(self, values: tuple[Any, ...]) -> None:
        r = dict(zip(FIELDS, nested_row(values), strict=True))
        t = float(r["t_s"])
        self.rows[round(t * 1000)] = r
        self.bridge.publish(VehicleTelemetry(
            t_s=t, phase=FlightPhase.DISARMED if r["landed"] else FlightPhase.MISSION,
            armed=not r["landed"], pos_w_m=_vec(r["pos_w_m"]),  # type: ignore[arg-type]
            vel_w_m_s=_vec(r["vel_w_m_s"]), q_wb=_vec(r["q_wb"]),  # type: ignore[arg-type]
            omega_b_rad_s=_vec(r["omega_b_rad_s"]),  # type: ignore[arg-type]
            rotor_speeds_hz=_vec(r["spin_hz"]),  # type: ignore[arg-type]
            tilt_rad=float(r["alpha_rad"]), battery_v=math.nan,
            health=SensorHealth(preflight_ok=True)))
        self.bridge.step(t)
        self.pump(0.0)

    def pump(self, timeout_s: float) -> bool:
        got = False
        while True:
            msg = (self.gcs.recv_match(blocking=True, timeout=timeout_s) if timeout_s > 0
                   else self.gcs.recv_match(blocking=False))
            if msg is None:
                return got
            if msg.get_type() != "BAD_DATA":
                self.received.append(msg)
                got = True
            timeout_s = 0.0


def test_that_a_lockstep_takeoff_reaches_the_gcs_at_the_configured_rates_with_its_values(
        ) -> None:
    # Fixture
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255)
    port = gcs.port.getsockname()[1]
    cfg = MavlinkConfig(uri=f"udpout:127.0.0.1:{port}", attitude_hz=50.0,
                        attitude_quaternion_hz=50.0, local_position_hz=25.0, odometry_hz=10.0,
                        actuator_output_hz=10.0)
    bridge = MavlinkBridge(cfg, RuleBasedCommandSink(FlightPhase.MISSION))
    sink = BridgeSink(bridge, gcs)
    try:
        # Test
        fly_mission(load_vehicle("fasthex"), Mission(load_mission("exp2b-roll-sine")),
                    load_disturbances("paper-calibrated"), seed=3, sink=sink,
                    duration_s=DURATION_S)
        sent = sum(bridge.stats().messages_out.values())
        while len(sink.received) < sent:
            assert sink.pump(TIMEOUT_S), f"{len(sink.received)} of {sent} messages arrived"
    finally:
        bridge.close()
        gcs.close()
    by_type: dict[str, list[Any]] = {}
    for m in sink.received:
        by_type.setdefault(m.get_type(), []).append(m)
    # Assert: rates in simulated time
    for kind, hz in cfg.rates_hz().items():
        assert abs(len(by_type[kind]) - hz * DURATION_S) <= 1, (kind, len(by_type[kind]))
    # values: each message equals the row of its own time stamp, in NED
    for att in by_type["ATTITUDE"]:
        row = sink.rows[att.time_boot_ms]
        expected = q_to_euler(q_world_to_ned(_vec(row["q_wb"])))  # type: ignore[arg-type]
        assert (att.roll, att.pitch, att.yaw) == pytest.approx(expected, abs=1e-5)
    zs = []
    for lp in by_type["LOCAL_POSITION_NED"]:
        row = sink.rows[lp.time_boot_ms]
        assert (lp.x, lp.y, lp.z) == pytest.approx(
            world_to_ned(_vec(row["pos_w_m"])), abs=1e-6)  # type: ignore[arg-type]
        zs.append(lp.z)
    for ao in by_type["ACTUATOR_OUTPUT_STATUS"]:
        row = sink.rows[round(ao.time_usec / 1000)]
        assert ao.actuator[:6] == pytest.approx(_vec(row["spin_hz"]), abs=1e-3)
        assert ao.actuator[6] == pytest.approx(float(row["alpha_rad"]), abs=1e-6)
    # the flight really took off: NED z (down) decreased by tens of centimetres
    assert zs[0] - min(zs) > 0.2
    assert max(max(ao.actuator[:6]) for ao in by_type["ACTUATOR_OUTPUT_STATUS"]) > 30.0
