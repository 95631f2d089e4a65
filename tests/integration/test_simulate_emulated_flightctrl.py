"""The flying simulator behind the real byte path: the emulated Flight-Ctrl in lockstep.

The test plays a minimal ground station over the pty (tk3 frames from the production codec):
it streams IMU samples, starts the motors and answers every sample with the controller's spin
rates. The emulator only knows the simulator through the ``EmulatedVehicle`` protocol, so this
checks that the simulator is a drop-in vehicle for the emulated backend.
"""

from __future__ import annotations

import math
import threading
import time

import pytest

from controller.geometric import GeometricController
from controller.missions import Mission
from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as mkm
from drivers.transport import open_transport
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from sim_backend.emulators.flightctrl import EmulatedFlightCtrl, FlightCtrlEmulatorConfig
from sim_backend.simulator import FastHexSimulator

TIMEOUT_S = 30.0


def test_that_the_controller_takes_off_through_the_emulated_flight_ctrl() -> None:
    # Fixture
    params = load_vehicle("fasthex")
    mission = Mission(load_mission("exp1-hover-tilt-steps"))
    sim = FastHexSimulator(params, load_disturbances("paper-calibrated"), seed=11,
                           start_pos_w_m=mission.start_pos_w_m)
    controller = GeometricController(params)
    lock = threading.Lock()
    parser = tk3.Tk3Parser()
    imus = 0
    # a long grace period: on a loaded machine the emulator must never free-run on its own
    config = FlightCtrlEmulatorConfig(clock="lockstep", lockstep_grace_s=TIMEOUT_S)
    with EmulatedFlightCtrl(sim, lock=lock, config=config) as emu:
        link = open_transport(f"pty://{emu.path}")
        try:
            link.write(tk3.encode_frame(mkm.StartMotors().encode()))
            link.write(tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 2000).encode()))
            deadline = time.monotonic() + TIMEOUT_S
            last_accel = (0.0, 0.0, 0.0)
            # Test: 3.5 s of the takeoff, one w frame per IMU sample
            while imus < 1750:
                assert time.monotonic() < deadline, f"only {imus} IMU samples"
                for raw in parser.feed(link.read(4096)):
                    msg = mkm.decode_board_message(raw)
                    if not isinstance(msg, mkm.ImuMessage):
                        continue
                    imus += 1
                    last_accel = msg.accel_m_s2
                    with lock:
                        t_s, state = sim.now_s(), sim.state()
                    cmd = controller.step(t_s, state, mission.reference(t_s), 0.0)
                    link.write(tk3.encode_frame(mkm.SpinRates.from_hz(cmd.spin_hz).encode()))
            with lock:
                t_s, pose, landed = sim.now_s(), sim.true_pose(), sim.landed
        finally:
            link.close()
    # Assert: airborne and on the takeoff profile (z_ref(3.5 s) = 0.85 m), IMU ~ 1 g
    assert not landed
    assert t_s == pytest.approx(3.5, abs=0.01)
    assert pose.pos_w_m[2] == pytest.approx(mission.reference(t_s).pos_w_m[2], abs=0.05)
    assert math.hypot(*last_accel) == pytest.approx(9.81, abs=1.5)
