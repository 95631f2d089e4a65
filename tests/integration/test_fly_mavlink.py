"""A lockstep flight seen and commanded by a second MAVLink endpoint (pymavlink), through the
bridge in the session's telemetry process."""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from flight_support import SHORT_MISSION, short_session
from pymavlink import mavutil

from groundstation.flight import FlightState
from groundstation.session import FlightSession


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_that_a_gcs_sees_the_flight_and_its_land_command_is_acknowledged(tmp_path: Path
                                                                          ) -> None:
    port = _free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    seen: dict[str, Any] = {"modes": [], "attitudes": 0, "acks": [], "texts": []}
    done = threading.Event()

    def gcs_main() -> None:
        sent_land = False
        while not done.is_set():
            msg = gcs.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "HEARTBEAT" and msg.get_srcSystem() == 1:
                seen["modes"].append(msg.custom_mode)
                if msg.custom_mode == int(FlightState.MISSION) and not sent_land:
                    gcs.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_NAV_LAND,
                                              0, 0, 0, 0, 0, 0, 0, 0)
                    sent_land = True
            elif kind == "ATTITUDE":
                seen["attitudes"] += 1
            elif kind == "COMMAND_ACK":
                seen["acks"].append((msg.command, msg.result))
            elif kind == "STATUSTEXT":
                seen["texts"].append(msg.text)

    thread = threading.Thread(target=gcs_main, daemon=True)
    thread.start()
    try:
        cfg, params, mission = short_session(tmp_path, mission=SHORT_MISSION.replace(
            "duration_s: 4.0", "duration_s: 60.0"))
        session = FlightSession(cfg, params, mission, record_path=tmp_path / "f.fhr",
                                echo_events=False, mavlink=f"udpout:127.0.0.1:{port}")
        out = session.run()
    finally:
        done.set()
        thread.join(timeout=5)
        gcs.close()
    reasons = [t.reason for t in out.result.transitions]
    # the 60 s hover was cut short by the GCS's land command, acknowledged as accepted
    assert "operator: land" in reasons, (seen["acks"], seen["modes"][-5:], seen["texts"][-5:])
    assert (mavutil.mavlink.MAV_CMD_NAV_LAND, mavutil.mavlink.MAV_RESULT_ACCEPTED) in seen["acks"]
    assert int(FlightState.MISSION) in seen["modes"]
    assert seen["attitudes"] > 10
    assert any("ARMED" in t for t in seen["texts"])
    assert out.result.transitions[-1].to_state is FlightState.DISARMED
