"""The full-pose geometric controller: Algorithm 1, R_d, position/attitude laws, saturation."""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller import compiled
from controller.geometric import (
    GeometricController,
    _control_law_compiled,
    bisect_tilt,
    control_law,
    desired_rotation,
)
from controller.missions import Mission
from controller.pipeline import FlightComputer
from controller.reference import (
    IDENTITY_Q,
    ZERO3,
    Reference,
    VehicleState,
    quat_from_axis_angle,
    quat_from_euler_zyx,
    quat_to_rot,
)
from groundstation.configs import load_mission, load_vehicle

PARAMS = load_vehicle("fasthex")
A30 = math.radians(30.0)
HOVER = (-0.14, -0.05, 1.0)


def _angle(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    dot = sum(x * y for x, y in zip(a, b, strict=True))
    na = math.sqrt(sum(x * x for x in a))
    nb = math.sqrt(sum(x * x for x in b))
    return math.acos(max(-1.0, min(1.0, dot / (na * nb))))


def _closed_form(b3r: tuple[float, float, float], f: tuple[float, float, float], r: float
                 ) -> float:
    fn = math.sqrt(sum(x * x for x in f))
    return max(0.0, _angle(b3r, f) - math.asin(min(1.0, r / fn)))


def _state(pos: tuple[float, float, float] = HOVER, q: tuple[float, ...] = IDENTITY_Q,
           omega: tuple[float, float, float] = ZERO3) -> VehicleState:
    return VehicleState(pos, ZERO3, q, omega)  # type: ignore[arg-type]


def _ref(q: tuple[float, ...] = IDENTITY_Q) -> Reference:
    return Reference(0.0, HOVER, ZERO3, ZERO3, q, ZERO3, 0.0)  # type: ignore[arg-type]


unit = st.floats(-1.0, 1.0)


@settings(max_examples=300, deadline=None)
@given(st.tuples(unit, unit, unit), st.tuples(st.floats(-20, 20), st.floats(-20, 20),
                                                st.floats(-40, 40)), st.floats(0.0, 8.0))
def test_that_the_bisection_matches_the_closed_form_of_paper_notes_item_7(
        b: tuple[float, float, float], f: tuple[float, float, float], r: float) -> None:
    # Fixture
    nb = math.sqrt(sum(x * x for x in b))
    fn = math.sqrt(sum(x * x for x in f))
    if nb < 0.1 or fn < 0.1:
        return
    b3r = (b[0] / nb, b[1] / nb, b[2] / nb)
    cross = (b3r[1] * f[2] - b3r[2] * f[1], b3r[2] * f[0] - b3r[0] * f[2],
             b3r[0] * f[1] - b3r[1] * f[0])
    # Test
    theta, b3d = bisect_tilt(b3r, f, r, 20)
    # Assert: (anti)parallel: no rotation axis, theta = 0 by decision (paper-notes item 6);
    # otherwise within theta_max / 2^21 <= pi / 2^21 = 1.5e-6 rad of the closed form
    if math.sqrt(sum(x * x for x in cross)) <= 1e-9 * fn:
        assert theta == 0.0
        return
    assert theta == pytest.approx(_closed_form(b3r, f, r), abs=2e-6)
    assert math.sqrt(sum(x * x for x in b3d)) == pytest.approx(1.0, abs=1e-12)
    assert _angle(b3r, b3d) == pytest.approx(theta, abs=1e-6)


def test_that_a_positive_theta_turns_b3r_towards_the_force() -> None:
    # Fixture: 5 N lateral demand, no lateral capability (UDT)
    f = (-5.0, 2.0, 30.0)
    # Test
    theta, b3d = bisect_tilt((0.0, 0.0, 1.0), f, 0.0, 20)
    # Assert: b3d ends up along f (swapping the cross product would turn it away)
    assert theta > 0.1
    assert _angle(b3d, f) < 1e-5


@pytest.mark.parametrize(("f", "r"), [((0.0, 0.0, 0.0), 0.0), ((0.0, 0.0, 30.0), 5.0),
                                      ((0.0, 0.0, -30.0), 5.0), ((1.0, 0.0, 0.5), 6.0)])
def test_that_degenerate_forces_give_no_tilt_and_no_nan(f: tuple[float, float, float],
                                                        r: float) -> None:
    # Test
    theta, b3d = bisect_tilt((0.0, 0.0, 1.0), f, r, 20)
    # Assert
    assert theta == pytest.approx(0.0, abs=1e-5)
    assert all(math.isfinite(x) for x in b3d)


@pytest.mark.parametrize("b3d", [(0.0, 0.0, 1.0), (0.3, -0.2, 0.9), (1.0, 0.0, 0.0),
                                 (-1.0, 1e-9, 0.0)])
def test_that_r_d_is_a_rotation_even_when_b3d_is_parallel_to_b1r(
        b3d: tuple[float, float, float]) -> None:
    # Test
    rd = desired_rotation(b3d, quat_to_rot(IDENTITY_Q))
    # Assert: orthonormal columns, det +1, third column along b3d
    cols = [(rd[i], rd[3 + i], rd[6 + i]) for i in range(3)]
    for i in range(3):
        for j in range(3):
            dot = sum(a * b for a, b in zip(cols[i], cols[j], strict=True))
            assert dot == pytest.approx(1.0 if i == j else 0.0, abs=1e-9)
    c0, c1, c2 = cols
    cross = (c0[1] * c1[2] - c0[2] * c1[1], c0[2] * c1[0] - c0[0] * c1[2],
             c0[0] * c1[1] - c0[1] * c1[0])
    assert cross == pytest.approx(c2, abs=1e-9)
    assert _angle(c2, b3d) < 1e-9


@pytest.mark.parametrize("alpha_deg", [0.0, 15.0, 30.0])
def test_that_hover_at_the_reference_commands_equal_spins_lifting_the_weight(
        alpha_deg: float) -> None:
    # Fixture
    sut = GeometricController(PARAMS)
    alpha = math.radians(alpha_deg)
    # Test
    cmd = sut.step(0.0, _state(), _ref(), alpha)
    # Assert: six equal thrusts whose vertical components carry m g
    expected = PARAMS.weight_n / (6.0 * math.cos(alpha))
    assert cmd.thrusts_n == pytest.approx([expected] * 6, rel=2e-3)
    assert cmd.spin_hz == pytest.approx([math.sqrt(expected / 9.9e-4)] * 6, rel=2e-3)
    assert not cmd.any_saturated


def test_that_in_udt_a_position_error_tilts_r_d_and_in_mdt_it_uses_lateral_force() -> None:
    # Fixture: 10 cm off in +x -> the controller wants -5 N along x
    off = (HOVER[0] + 0.1, HOVER[1], HOVER[2])
    udt, mdt = GeometricController(PARAMS), GeometricController(PARAMS)
    # Test
    c_udt = udt.step(0.0, _state(off), _ref(), 0.0)
    c_mdt = mdt.step(0.0, _state(off), _ref(), A30)
    # Assert
    assert c_udt.r_xy_n == 0.0
    assert c_udt.u_f_b_n[0] == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(c_udt.theta_rad) == pytest.approx(math.degrees(math.atan2(5.0, 30.411)),
                                                          abs=1e-3)
    assert c_udt.r_wd[2] < 0.0  # b3d leans towards -x
    assert c_mdt.r_xy_n == pytest.approx(5.32, abs=0.05)
    assert c_mdt.u_f_b_n[0] == pytest.approx(-5.0, abs=1e-9)
    assert c_mdt.theta_rad == pytest.approx(0.0, abs=1e-5)


def test_that_the_lateral_force_is_saturated_to_the_cylinder() -> None:
    # Fixture: 30 cm off: 15 N lateral demand, bound ~5.3 N at 30 deg
    sut = GeometricController(PARAMS)
    # Test
    cmd = sut.step(0.0, _state((HOVER[0] + 0.3, HOVER[1], HOVER[2])), _ref(), A30)
    # Assert
    assert math.hypot(cmd.u_f_b_n[0], cmd.u_f_b_n[1]) == pytest.approx(cmd.r_xy_n, rel=1e-9)
    assert cmd.theta_rad > 0.1  # the rest is obtained by tilting


def test_that_the_integrals_are_bounded() -> None:
    # Fixture
    sut = GeometricController(PARAMS)
    lim = PARAMS.controller.pos_integral_limit_m_s
    # Test: 1 m error for 60 s
    for k in range(3000):
        sut.step(k * 0.02, _state((HOVER[0] + 1.0, HOVER[1], HOVER[2] - 1.0),
                                  quat_from_axis_angle((1.0, 0.0, 0.0), 0.5)), _ref(), A30)
    # Assert
    assert sut.memory.e_pi_m_s[0] == pytest.approx(lim[0])
    assert sut.memory.e_pi_m_s[2] == pytest.approx(-lim[2])
    assert abs(sut.memory.e_ri_rad_s[0]) == pytest.approx(
        PARAMS.controller.att_integral_limit_rad_s[0])


def test_that_the_attitude_law_pushes_back_against_a_roll_error() -> None:
    # Fixture: body rolled +0.1 rad, spinning +1 rad/s about x
    sut = GeometricController(PARAMS)
    q = quat_from_euler_zyx(0.1, 0.0, 0.0)
    # Test
    cmd = sut.step(0.0, _state(q=q, omega=(1.0, 0.0, 0.0)), _ref(), A30)
    # Assert: e_R = +0.1 about x (vee of the skew part), u_tau = -K_R e_R - K_w w
    assert cmd.e_r_rad[0] == pytest.approx(math.sin(0.1), rel=1e-6)
    assert cmd.u_tau_b_n_m[0] == pytest.approx(-15.0 * math.sin(0.1) - 1.5, rel=1e-6)


def test_that_spin_rates_are_clamped_and_flagged() -> None:
    # Fixture: a huge position error and a large attitude error
    sut = GeometricController(PARAMS)
    q = quat_from_euler_zyx(0.6, -0.5, 1.0)
    # Test
    cmd = sut.step(0.0, _state((5.0, -5.0, -3.0), q, (3.0, -2.0, 4.0)), _ref(), A30)
    # Assert
    assert cmd.any_saturated
    assert all(16.0 <= w <= 102.0 for w in cmd.spin_hz)
    for w, flag in zip(cmd.spin_hz, cmd.saturated, strict=True):
        assert flag == (w in (16.0, 102.0))


def test_that_the_feedforward_mode_is_off_in_the_paper_faithful_config() -> None:
    assert PARAMS.controller.attitude_feedforward is False


def test_that_the_feedforward_mode_damps_the_rate_relative_to_the_reference() -> None:
    # Fixture: on the reference attitude, turning with the reference at 0.5 rad/s about x
    ff = dataclasses.replace(PARAMS, controller=dataclasses.replace(
        PARAMS.controller, attitude_feedforward=True))
    ref = Reference(0.0, HOVER, ZERO3, ZERO3, IDENTITY_Q, (0.5, 0.0, 0.0), A30)
    state = _state(omega=(0.5, 0.0, 0.0))
    # Test
    with_ff = GeometricController(ff).step(0.0, state, ref, A30)
    paper = GeometricController(PARAMS).step(0.0, state, ref, A30)
    # Assert: the paper's law damps the whole rate (-K_w w), the feed-forward mode nothing
    assert with_ff.u_tau_b_n_m == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert paper.u_tau_b_n_m[0] == pytest.approx(-1.5 * 0.5)


def test_that_a_warmed_up_flight_computer_steps_first_on_built_caches() -> None:
    # Fixture: the ground station warms the computer before arming; the first step at
    # TAKEOFF must not build the wrench map or the thrust axes (~1 ms of numpy and JIT)
    mission = Mission(load_mission("exp1-hover-tilt-steps"))
    sut = FlightComputer(PARAMS, mission)
    alpha = sut.planner.alpha_cmd_rad
    state = VehicleState(mission.start_pos_w_m, ZERO3, IDENTITY_Q, ZERO3)
    # Test
    sut.warm_up()
    built = sut.controller.mapper.recomputations
    axes_alpha = sut._axes_alpha
    stepped = sut.controller.memory.last_t_s
    sut.step(0.0, state, alpha)
    sut.thrust_force_b(alpha, (1.0,) * 6)
    # Assert: both caches were there before the step, and the step reused them
    assert built == 1
    assert axes_alpha == alpha
    assert sut.controller.mapper.recomputations == 1
    assert stepped is None  # the warm-up stepped nothing


_FEEDFORWARD_CONTROLLER = GeometricController(dataclasses.replace(
    PARAMS, controller=dataclasses.replace(PARAMS.controller, attitude_feedforward=True,
                                           force_feedforward=True)))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-2.0, 2.0), min_size=29, max_size=29),
       st.floats(0.0, 20.0), st.booleans(), st.floats(0.0, 0.6))
def test_that_the_compiled_control_law_equals_its_python_source(
        values: list[float], r_xy: float, feed: bool, alpha: float) -> None:
    # Fixture: any state and reference (attitudes normalised), any bound and tilt
    if not compiled.AVAILABLE:
        pytest.skip("numba not installed: the Python source is all there is")
    sut = _FEEDFORWARD_CONTROLLER
    v = list(values)
    for i in (6, 22):
        n = math.sqrt(sum(x * x for x in v[i:i + 4])) or 1.0
        v[i:i + 4] = [x / n for x in v[i:i + 4]] if n != 1.0 else [1.0, 0.0, 0.0, 0.0]
    rest = (r_xy, feed, 0.3, -0.2, 0.1, 0.01, -0.02, 0.03, 0.001, 0.002, -0.003)
    # Test
    got = _control_law_compiled(sut._k, sut.mapper.rows_array(alpha), 20, 0.002, *v, *rest)
    want = control_law(tuple(sut._k.tolist()), sut.mapper.rows(alpha), 20, 0.002, *v, *rest)
    # Assert: the same operations in the same order, the same numbers
    assert got == want


def test_that_a_rehearsal_changes_none_of_the_computers_ticks() -> None:
    # Fixture: two computers of Exp. 1 (its tilt steps exercise the planner and the map
    # cache), one rehearsed before its first tick; a state that moves and an external force
    mission = Mission(load_mission("exp1-hover-tilt-steps", vehicle=PARAMS))
    plain = FlightComputer(PARAMS, mission)
    rehearsed = FlightComputer(PARAMS, mission)
    rehearsed.rehearse()
    # Test + Assert: every output of 4000 ticks (8 s) equal bit for bit
    alpha = 0.0
    for k in range(4000):
        t = 0.002 * k
        s = VehicleState((HOVER[0] + 0.01 * math.sin(t), HOVER[1], HOVER[2] - 0.02 * math.cos(t)),
                         (0.01 * math.cos(t), 0.0, 0.02 * math.sin(t)),
                         quat_from_axis_angle((0.0, 0.0, 1.0), 0.01 * math.sin(3 * t)),
                         (0.0, 0.02 * math.cos(2 * t), 0.0))
        a = plain.step(t, s, alpha, force_ext_w_n=(0.1, 0.0, -0.2))
        b = rehearsed.step(t, s, alpha, force_ext_w_n=(0.1, 0.0, -0.2))
        assert a == b, k
        assert plain.thrust_force_b(alpha, a.cmd.thrusts_n) == \
            rehearsed.thrust_force_b(alpha, b.cmd.thrusts_n)
        alpha += max(-0.0005, min(0.0005, a.alpha_cmd_rad - alpha))  # the servo follows
    assert plain.controller.memory == rehearsed.controller.memory
