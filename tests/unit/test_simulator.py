"""The flying simulator: physics from first principles against the model, contact, sensors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.model import VehicleModel, cardan_tilts_rad
from controller.params import VehicleParams
from drivers.mikrokopter.device import FlightCtrlConfig
from groundstation.configs import load_disturbances, load_vehicle
from sim_backend import physics
from sim_backend.simulator import FastHexSimulator, cardan_tilts
from sim_backend.vehicle import EmulatedVehicle

PARAMS = load_vehicle("fasthex")
MODEL = VehicleModel(PARAMS)
IDEAL = load_disturbances("ideal")
CALIBRATED = load_disturbances("paper-calibrated")


def _hover_spins(alpha_rad: float) -> list[float]:
    return [float(w) for w in MODEL.spin_from_thrust(MODEL.hover_thrusts(alpha_rad))]


def test_that_the_simulator_is_an_emulated_vehicle() -> None:
    assert isinstance(FastHexSimulator(PARAMS, IDEAL), EmulatedVehicle)


@pytest.mark.parametrize("alpha_deg", [0.0, 7.3, 20.0, 34.9])
def test_that_the_plain_float_cardan_chain_matches_the_model(alpha_deg: float) -> None:
    # Fixture
    k, bend = PARAMS.tilt.worm_ratio, math.radians(PARAMS.tilt.cardan_bend_deg)
    # Test / Assert
    assert cardan_tilts(math.radians(alpha_deg), k, math.cos(bend)) == pytest.approx(
        list(cardan_tilts_rad(math.radians(alpha_deg), k, bend)), abs=1e-12)


def test_that_it_rests_on_the_ground_with_motors_off_and_the_imu_reads_gravity() -> None:
    # Fixture
    sut = FastHexSimulator(PARAMS, IDEAL, start_pos_w_m=(1.0, 2.0, 0.1))
    # Test
    sut.advance(1.0)
    # Assert
    assert sut.landed
    assert sut.true_pose().pos_w_m == (1.0, 2.0, 0.1)
    imu = sut.read_imu()
    assert imu.accel_m_s2 == pytest.approx((0.0, 0.0, 9.81))
    assert imu.gyro_rad_s == (0.0, 0.0, 0.0)
    assert sut.now_s() == pytest.approx(1.0)


@pytest.mark.parametrize("alpha_deg", [0.0, 30.0])
def test_that_the_per_propeller_wrench_equals_the_allocation_model(alpha_deg: float) -> None:
    # Fixture: ideal preset = the controller's model; lift off with some spin difference
    alpha = math.radians(alpha_deg)
    sut = FastHexSimulator(PARAMS, IDEAL)
    sut.command_tilt_rad(alpha)
    sut.advance(alpha / math.radians(10.0) + 0.1)  # let the servo get there
    spins = [w * f for w, f in zip(_hover_spins(alpha), (1.06, 1.0, 1.03, 1.0, 1.05, 1.01),
                                   strict=True)]
    sut.command_rotor_speeds_hz(spins)
    # Test: one short step from rest
    s0 = sut.state()
    sut.advance(1e-3)
    s1 = sut.state()
    # Assert: accelerations = the model's F u (body = world here, level start)
    wrench = MODEL.allocation(alpha) @ MODEL.thrust_from_spin(spins)
    acc = [(b - a) / 1e-3 for a, b in zip(s0.vel_w_m_s, s1.vel_w_m_s, strict=True)]
    domega = [(b - a) / 1e-3 for a, b in zip(s0.omega_b_rad_s, s1.omega_b_rad_s, strict=True)]
    assert acc == pytest.approx([wrench[0] / 3.1, wrench[1] / 3.1, wrench[2] / 3.1 - 9.81],
                                rel=1e-3, abs=1e-3)
    assert domega == pytest.approx(list(wrench[3:] / np.array(PARAMS.inertia_diag_kg_m2)),
                                   rel=1e-3, abs=1e-3)


def _climbed_then_descending() -> tuple[FastHexSimulator, float]:
    """In the air: 3 % more thrust than hover for 1 s, then 5 % less (it comes down); the
    simulator and the height reached (m)."""
    sut = FastHexSimulator(PARAMS, IDEAL)
    hover = _hover_spins(0.0)
    sut.command_rotor_speeds_hz([w * 1.015 for w in hover])
    sut.advance(1.0)
    climbed = sut.true_pose().pos_w_m[2]
    sut.command_rotor_speeds_hz([w * 0.95 for w in hover])
    return sut, climbed


def test_that_it_lifts_off_climbs_and_lands_at_rest() -> None:
    # Test: 3 % more thrust than hover for 1 s, then less until it lands
    sut, climbed = _climbed_then_descending()
    for _ in range(500):
        sut.advance(0.01)
        if sut.landed:
            break
    # Assert: z = 0.1 + a t^2 / 2 with a = (1.015^2 - 1) g
    assert climbed - 0.1 == pytest.approx(0.5 * (1.015**2 - 1.0) * 9.81, rel=1e-2)
    assert sut.landed
    assert len(sut.touchdown_speeds_m_s) == 1 and sut.touchdown_speeds_m_s[0] > 0.0
    assert sut.state().vel_w_m_s == (0.0, 0.0, 0.0)
    assert sut.true_pose().pos_w_m[2] == pytest.approx(0.1)


def test_that_the_accelerometer_feels_the_touchdown_that_stops_the_body() -> None:
    # Fixture: the climb and descent above, sampled as the IMU is (2 ms)
    sut, _ = _climbed_then_descending()
    v_climb = sut.state().vel_w_m_s[2]
    dt, g = 0.002, PARAMS.gravity_m_s2
    felt = []   # the vertical acceleration the accelerometer reads (level flight: body z)
    landed_at = None
    for k in range(5000):
        sut.advance(dt)
        felt.append(sut.specific_force_b()[2] - g)
        if sut.landed and landed_at is None:
            landed_at = k
        if landed_at is not None and k > landed_at + 50:   # 0.1 s on the ground
            break
    # Assert: what it felt integrates to the body's change of speed, the stop included (a
    # contact that only clamps the body felt nothing: a dead reckoning went on sinking at the
    # touchdown speed); spread over the gear's CONTACT_S, then the ground's reaction, g
    speed = sut.touchdown_speeds_m_s[0]
    assert speed > 0.3
    assert sum(felt) * dt == pytest.approx(0.0 - v_climb, abs=0.01)
    assert max(felt) == pytest.approx(speed / physics.CONTACT_S, rel=0.05)
    assert felt[-1] == pytest.approx(0.0, abs=1e-9)


def test_that_the_gyro_feels_the_touchdown_that_levels_the_body() -> None:
    # Fixture: the descent above with the body rolling (a blow to an arm) so that it touches
    # down tilted; the contact levels it at once, which the gyro must read as a real gear's
    # levelling (the rate spread over CONTACT_S): a dead reckoning kept the tilt, and g times
    # that tilt drove its horizontal estimate away on the ground (0.7 m in 2.6 s)
    sut, _ = _climbed_then_descending()
    sut.advance(0.3)
    sut.kick_body_rate((0.3, 0.0, 0.0))
    q = np.array(sut.state().q_wb, dtype=float)   # attitude dead reckoned on the gyro
    dt = 0.002
    landed_at = None
    rates = []
    for k in range(5000):
        sut.advance(dt)
        rates.append(sut.read_imu().gyro_rad_s)
        w = np.array(rates[-1]) * dt     # IDEAL: no noise, no bias
        angle = float(np.linalg.norm(w))
        dq = np.r_[math.cos(angle / 2), (w / angle) * math.sin(angle / 2)] if angle else \
            np.array([1.0, 0.0, 0.0, 0.0])
        q = np.array([q[0] * dq[0] - q[1:] @ dq[1:],
                      *(q[0] * dq[1:] + dq[0] * q[1:] + np.cross(q[1:], dq[1:]))])
        if sut.landed and landed_at is None:
            landed_at = k
            tilt_deg = math.degrees(2 * math.acos(min(1.0, math.hypot(q[0], q[3]))))
        if landed_at is not None and k > landed_at + physics.LEVEL_S / dt + 5:
            break
    # Assert: it touched down tilted, and the gyro's attitude ends level as the body is
    assert tilt_deg > 2.0
    final = np.array(sut.state().q_wb)
    err_deg = math.degrees(2 * math.acos(min(1.0, abs(float(final @ q)))))
    assert err_deg < 0.05
    # without a step the Flight-Ctrl driver would drop as a corrupted byte (but the body rate
    # itself, zeroed by the contact)
    after = np.array(rates[landed_at + 1:])
    assert np.abs(np.diff(after, axis=0)).max() < FlightCtrlConfig().max_gyro_step_rad_s


def test_that_the_imu_dead_reckons_a_tilted_touchdown_to_rest() -> None:
    # Fixture: the tilted touchdown above, dead reckoned on the whole IMU: attitude on the
    # gyro, velocity on the accelerometer turned into the world by that attitude. The body
    # levels within a step and the gyro over LEVEL_S; an accelerometer that read the level
    # frame meanwhile told the dead reckoning it was pushed sideways by g sin(tilt) (seen:
    # 0.2 m/s after a 9.5 deg touchdown, which the loop then took for MoCap being wrong)
    sut, _ = _climbed_then_descending()
    sut.advance(0.3)
    sut.kick_body_rate((0.3, 0.0, 0.0))
    q = np.array(sut.state().q_wb, dtype=float)
    v = np.array(sut.state().vel_w_m_s, dtype=float)
    dt, g = 0.002, PARAMS.gravity_m_s2
    landed_at = None
    for k in range(5000):
        sut.advance(dt)
        imu = sut.read_imu()
        w = np.array(imu.gyro_rad_s) * dt
        angle = float(np.linalg.norm(w))
        dq = np.r_[math.cos(angle / 2), (w / angle) * math.sin(angle / 2)] if angle else \
            np.array([1.0, 0.0, 0.0, 0.0])
        q = np.array([q[0] * dq[0] - q[1:] @ dq[1:],
                      *(q[0] * dq[1:] + dq[0] * q[1:] + np.cross(q[1:], dq[1:]))])
        qw, qv = q[0], q[1:]
        f_b = np.array(imu.accel_m_s2)
        f_w = f_b + 2 * qw * np.cross(qv, f_b) + 2 * np.cross(qv, np.cross(qv, f_b))
        v += (f_w - (0.0, 0.0, g)) * dt
        if sut.landed and landed_at is None:
            landed_at = k
            v_landing = v.copy()
        if landed_at is not None and k > landed_at + physics.LEVEL_S / dt + 5:
            break
    # Assert: it came down fast and sideways, and the IMU says it is at rest (as it is)
    assert sut.touchdown_speeds_m_s[0] > 0.3 and math.hypot(*v_landing[:2]) > 0.05
    assert sut.state().vel_w_m_s == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(v, 0.0, atol=0.01)


def test_that_rotor_speeds_lag_with_the_configured_time_constant() -> None:
    # Fixture
    sut = FastHexSimulator(PARAMS, CALIBRATED)
    # Test
    sut.command_rotor_speeds_hz([50.0] * 6)
    sut.advance(0.03)
    # Assert: 1 - 1/e after one time constant
    assert sut.rotor_speeds_hz() == pytest.approx([50.0 * (1.0 - math.exp(-1.0))] * 6, rel=1e-6)


def test_that_the_servo_moves_at_the_tilt_rate_limit_and_the_cardan_chain_bends_tilts() -> None:
    # Fixture
    sut = FastHexSimulator(PARAMS, CALIBRATED)
    # Test
    sut.command_tilt_rad(math.radians(30.0))
    sut.advance(1.0)
    mid = sut.tilt_rad()
    sut.advance(3.0)
    # Assert
    assert math.degrees(mid) == pytest.approx(10.0, abs=1e-6)
    assert math.degrees(sut.tilt_rad()) == pytest.approx(30.0)
    tilts = np.degrees(np.abs(sut.propeller_tilts_rad()))
    assert np.max(np.abs(tilts - 30.0)) > 0.05  # the chain makes them differ
    assert np.max(np.abs(tilts - 30.0)) < 1.05


def test_that_same_seeds_fly_the_same_and_different_seeds_differ() -> None:
    # Fixture
    def fly(seed: int) -> tuple[float, ...]:
        sut = FastHexSimulator(PARAMS, CALIBRATED, seed=seed)
        sut.command_rotor_speeds_hz([w * 1.02 for w in _hover_spins(0.0)])
        sut.advance(1.5)
        return sut.true_pose().pos_w_m + sut.read_imu().gyro_rad_s

    # Test / Assert
    assert fly(3) == fly(3)
    assert fly(3) != fly(4)


def test_that_the_ou_force_has_the_configured_rms() -> None:
    # Fixture: only the OU force, sampled after each step while resting in the air
    preset = dataclasses.replace(IDEAL, ou_force_rms_n=0.3, ou_force_tau_s=0.05)
    sut = FastHexSimulator(PARAMS, preset, seed=1)
    sut.command_rotor_speeds_hz(_hover_spins(0.0))
    samples = []
    for _ in range(4000):
        sut.advance(0.01)
        samples.append(sut.external_force_w_n())
    # Assert: rms of the vector ~0.3 N (2000 correlation times -> ~3 % sampling error)
    rms = math.sqrt(float(np.mean(np.sum(np.square(samples), axis=1))))
    assert rms == pytest.approx(0.3, rel=0.1)


def test_that_tilting_rotors_exert_gyroscopic_torques_that_cancel_only_when_symmetric(
        ) -> None:
    # Fixture: the same airborne flight with and without rotor inertia, tilting at 10 deg/s
    def omega_after_tilting(inertia: float, boost: tuple[float, ...]) -> np.ndarray:
        sut = FastHexSimulator(PARAMS, dataclasses.replace(IDEAL, rotor_inertia_kg_m2=inertia))
        sut.command_rotor_speeds_hz([w * b for w, b in zip(_hover_spins(0.0), boost,
                                                           strict=True)])
        sut.advance(0.05)
        sut.command_tilt_rad(math.radians(30.0))
        sut.advance(0.2)
        return np.array(sut.state().omega_b_rad_s)

    symmetric = (1.05,) * 6
    one_fast = (1.2, 1.05, 1.05, 1.05, 1.05, 1.05)
    # Test
    sym = omega_after_tilting(1.5e-4, symmetric) - omega_after_tilting(0.0, symmetric)
    asym = omega_after_tilting(1.5e-4, one_fast) - omega_after_tilting(0.0, one_fast)
    # Assert: alternating spins and tilts cancel the rotors' momenta; one faster rotor leaves
    # I_r 2 pi dw alpha_dot ~ 2e-3 N m (-> ~5e-3 rad/s after 0.2 s), plus the w x h coupling
    # of the unbalanced momentum with the rates the thrust imbalance causes
    assert np.max(np.abs(sym)) < 1e-9
    assert 1e-3 < np.max(np.abs(asym)) < 0.1


def test_that_mocap_frames_come_at_the_rate_with_latency_and_dropouts() -> None:
    # Fixture
    preset = dataclasses.replace(CALIBRATED, mocap_dropout_prob=0.1)
    sut = FastHexSimulator(PARAMS, preset, seed=2)
    # Test
    frames = []
    for _ in range(2000):
        sut.advance(0.002)
        for f in sut.poll_mocap():
            assert sut.now_s() - f.t_s >= 0.01 - 1e-9  # latency honoured
            frames.append(f)
    # Assert: 4 s at 100 Hz minus ~10 % dropped, sub-mm noise around the true pose
    assert 330 <= len(frames) <= 390
    assert sut.mocap.dropped == sut.mocap.captured - len(frames) - len(sut.mocap._pending)
    err = [math.dist(f.pos_w_m, (0.0, 0.0, 0.1)) for f in frames]
    assert 0.0 < float(np.mean(err)) < 0.002


def test_that_imu_noise_matches_the_noise_density() -> None:
    # Fixture
    sut = FastHexSimulator(PARAMS, CALIBRATED, seed=5)
    # Test
    g = np.array([sut.read_imu().gyro_rad_s for _ in range(5000)])
    # Assert: std = density * sqrt(rate / 2); mean = the constant bias
    assert np.std(g, axis=0) == pytest.approx([8.7e-4 * math.sqrt(250.0)] * 3, rel=0.05)
    assert np.mean(g, axis=0) == pytest.approx(sut.imu.gyro_bias_rad_s, abs=1e-3)


@pytest.mark.parametrize("rate_hz", [500.0, 1000.0])
def test_that_imu_noise_follows_the_rate_it_is_sampled_at(rate_hz: float) -> None:
    # Fixture: the preset says 500 Hz; an emulated board asked for 1 kHz by its host samples
    # every 1 ms (its noise was sized for 500 Hz: sqrt(2) too quiet, a 1 kHz loop flattered)
    sut = FastHexSimulator(PARAMS, CALIBRATED, seed=5)
    assert CALIBRATED.imu_rate_hz == 500.0
    g = []
    # Test
    for _ in range(5000):
        sut.advance(1.0 / rate_hz)
        g.append(sut.read_imu().gyro_rad_s)
    # Assert: std = density * sqrt(rate / 2) at the rate sampled
    assert np.std(g, axis=0) == pytest.approx([8.7e-4 * math.sqrt(rate_hz / 2.0)] * 3,
                                              rel=0.05)


def test_that_the_jitted_physics_equals_its_python_source() -> None:
    # Fixture: flying, the servo moving, every disturbance on; the plain-Python functions are
    # what runs where numba is absent
    if not physics.AVAILABLE:
        pytest.skip("numba not installed: the Python source is all there is")
    sim = FastHexSimulator(PARAMS, CALIBRATED, seed=4)
    sim.command_rotor_speeds_hz([80.0] * 6)
    sim.advance(0.5)
    rng = np.random.default_rng(1)
    normals, wrenches = rng.standard_normal(30), np.zeros((10, physics.N_WRENCH))
    wrenches[3:] = [1.0, 0.5, -0.2, 0.1, 0.3, 0.0, -0.1, 0.02, 0.0, 0.01, 0.0, 0.03, -0.01]
    states, outs = [], []
    advance_py = physics.advance.py_func  # type: ignore[attr-defined]
    for fn in (physics.advance, advance_py):
        s, out = sim._s.copy(), np.empty((10, physics.N_OUT))
        # Test
        fn(s, sim._p, 1e-3, 10, normals, 0, wrenches, 0.5, 0.01, out, 85.0, 80.0, 75.0, 80.0,
           85.0, 90.0, math.radians(20.0))
        states.append(s)
        outs.append(out)
    # Assert: the same operations in the same order
    np.testing.assert_array_equal(states[0], states[1])
    np.testing.assert_array_equal(outs[0], outs[1])


#: propeller 1 clockwise: valid only with tilts below atan(c_tau/l) = 3.56 deg (the physics
#: below is evaluated at any tilt through the state)
MIRRORED = dataclasses.replace(
    PARAMS, rotors=dataclasses.replace(PARAMS.rotors, first_rotor_ccw=False),
    tilt=dataclasses.replace(PARAMS.tilt, max_tilt_deg=3.0))
ROTOR_INERTIA = 1.5e-4
ROTOR_LAG_S = 0.03


def _rotor_sim(params: VehicleParams) -> FastHexSimulator:
    preset = dataclasses.replace(IDEAL, rotor_inertia_kg_m2=ROTOR_INERTIA,
                                 rotor_time_constant_s=ROTOR_LAG_S)
    return FastHexSimulator(params, preset)


def _angular_acceleration(sim: FastHexSimulator, alpha: float, w: np.ndarray,
                          w_cmd: np.ndarray, omega: tuple[float, float, float],
                          tilting: bool, h: float = 1e-6) -> np.ndarray:
    """d omega/dt of the body (airborne, level) over one physics substep of ``h`` seconds."""
    s = sim._s
    s[physics.S_LANDED] = 0.0
    s[physics.S_X:physics.S_X + 13] = [0, 0, 5, 0, 0, 0, 1, 0, 0, 0, *omega]
    s[physics.S_SERVO] = alpha
    physics.set_tilts(s, sim._p, alpha)
    s[physics.S_W:physics.S_W + 6] = w
    goal = alpha + (1.0 if tilting else 0.0)
    physics.advance(s, sim._p, h, 1, np.zeros(3), 0, np.zeros((1, physics.N_WRENCH)), 1e9,
                    1.0, np.empty((1, physics.N_OUT)), *(float(x) for x in w_cmd), goal)
    return (s[physics.S_X + 10:physics.S_X + 13] - np.array(omega)) / h


def _first_principles_angular_acceleration(
        ccw: bool, alpha: float, w: np.ndarray, w_dot: np.ndarray,
        omega: tuple[float, float, float], alpha_dot: float) -> np.ndarray:
    """Propeller i spins at s_i w_i about its axis n_i (s_i = +1: counter-clockwise seen from
    above the rotor, (-1)^(i-1) when propeller 1 is CCW); its angular momentum is
    H_i = J_r 2 pi s_i w_i n_i. The motor reacts on the body with minus what it gives the
    rotor: the drag it overcomes (-s_i c_tau f_i n_i) and dH_i/dt in B
    (J_r 2 pi s_i (w_i' n_i + w_i n_i')); Euler: J w' = tau - w x (J w + sum H_i)."""
    l_m, c_f, c_tau = (PARAMS.geometry.arm_length_m, PARAMS.rotors.thrust_coeff_n_per_hz2,
                       PARAMS.rotors.drag_coeff_m)
    inertia = np.diag(PARAMS.inertia_diag_kg_m2)
    torque, momentum = np.zeros(3), np.zeros(3)
    for i in range(6):
        t = 1.0 if i % 2 == 0 else -1.0
        spin = t if ccw else -t
        yaw = i * math.pi / 3.0
        rz = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0],
                       [0.0, 0.0, 1.0]])
        n = rz @ np.array([0.0, -math.sin(t * alpha), math.cos(t * alpha)])
        n_dot = rz @ np.array([0.0, -math.cos(t * alpha), -math.sin(t * alpha)]) * t * alpha_dot
        f = c_f * w[i] ** 2
        pos = l_m * np.array([math.cos(yaw), math.sin(yaw), 0.0])
        k = ROTOR_INERTIA * 2.0 * math.pi * spin
        torque += np.cross(pos, f * n) - spin * c_tau * f * n - k * (w_dot[i] * n + w[i] * n_dot)
        momentum += k * w[i] * n
    om = np.array(omega)
    return np.asarray(np.linalg.solve(inertia, torque - np.cross(om, inertia @ om + momentum)))


@pytest.mark.parametrize("ccw", [True, False], ids=["ccw", "cw"])
@pytest.mark.parametrize("alpha_deg", [0.0, 10.0, 30.0])
@pytest.mark.parametrize("case", ["steady", "spin-up", "body rate", "tilting"])
def test_that_the_rotor_torques_follow_the_spin_direction_from_first_principles(
        ccw: bool, alpha_deg: float, case: str) -> None:
    # Fixture: uneven rotor speeds (net angular momentum), each term switched on alone
    sut = _rotor_sim(PARAMS if ccw else MIRRORED)
    alpha = math.radians(alpha_deg)
    w = np.array([72.0, 65.0, 80.0, 70.0, 76.0, 61.0])
    w_cmd = w + (np.array([30.0, -25.0, 20.0, 35.0, -30.0, 15.0]) if case == "spin-up" else 0.0)
    omega = (0.4, -0.3, 0.7) if case == "body rate" else (0.0, 0.0, 0.0)
    alpha_dot = math.radians(PARAMS.tilt.max_rate_deg_s) if case == "tilting" else 0.0
    h = 1e-6
    # Test
    got = _angular_acceleration(sut, alpha, w, w_cmd, omega, case == "tilting", h)
    # Assert: the substep uses the rotor speeds after it (w + (w_cmd - w) h / tau), a thrust
    # error of 2 c_f w dw per rotor on lever arms < l + c_tau; the terms checked are far larger
    # (spin-up reaction ~ J_r 2 pi 35 Hz / 30 ms = 1.1 N m, the gyroscopic terms >~ 1e-3 N m)
    expected = _first_principles_angular_acceleration(ccw, alpha, w, (w_cmd - w) / ROTOR_LAG_S,
                                                      omega, alpha_dot)
    dw = np.max(np.abs(w_cmd - w)) * h / ROTOR_LAG_S
    lever = PARAMS.geometry.arm_length_m + PARAMS.rotors.drag_coeff_m
    bound = 6.0 * lever * 2.0 * PARAMS.rotors.thrust_coeff_n_per_hz2 * float(np.max(w_cmd)) * dw \
        / min(PARAMS.inertia_diag_kg_m2)
    np.testing.assert_allclose(got, expected, rtol=0.0, atol=bound + 1e-5)


@pytest.mark.parametrize(("ccw", "reverses"), [(True, False), (False, True)], ids=["ccw", "cw"])
def test_that_a_yaw_command_first_yaws_the_wrong_way_only_with_propeller_1_clockwise(
        ccw: bool, reverses: bool) -> None:
    # Fixture: at 10 deg tilt, speed up propellers 1, 3, 5 and slow down 2, 4, 6 by 2 Hz: the
    # steady yaw torque (after the 30 ms lag) against the first instant's (the spin-up reaction
    # alone, J_r 2 pi 2 Hz / 30 ms on each rotor's axis)
    sut = _rotor_sim(PARAMS if ccw else MIRRORED)
    alpha = math.radians(10.0)
    w0 = np.full(6, 72.0)
    step = 2.0 * np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    # Test
    first = _angular_acceleration(sut, alpha, w0, w0 + step, (0.0, 0.0, 0.0), False)[2]
    steady = _angular_acceleration(sut, alpha, w0 + step, w0 + step, (0.0, 0.0, 0.0), False)[2]
    # Assert: propeller 1 CW puts the tilted thrust's yaw (l sin a) against the drag torque and
    # the spin-up reaction (c_tau cos a, the same sign): a right-half-plane zero
    reaction = 6.0 * ROTOR_INERTIA * 2.0 * math.pi * 2.0 / ROTOR_LAG_S * math.cos(alpha) \
        / PARAMS.inertia_diag_kg_m2[2]
    assert abs(first) == pytest.approx(reaction, rel=1e-3)
    assert bool(first * steady < 0.0) is reverses
