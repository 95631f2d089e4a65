"""TiltServo's pure parts: URI, geometry through the worm, goal rate limit, config checks."""

from __future__ import annotations

import math
import multiprocessing as mp
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st
from process_targets import hammer_mailbox

from config.schema import ConfigError, load_config_text
from drivers.dynamixel.control_table import ErrorBit
from drivers.dynamixel.device import (
    _S,
    TiltServo,
    TiltServoConfig,
    _Mailbox,
    error_names,
    parse_servo_uri,
    rate_limited_goal,
    steps_to_tilt,
    tilt_to_steps,
)
from drivers.errors import TransportUriError


def test_that_serial_pty_and_bare_uris_give_port_baud_and_id() -> None:
    uri = parse_servo_uri("serial:///dev/ttyUSB1?baud=1000000&id=1")
    assert (uri.port, uri.baud, uri.dxl_id) == ("/dev/ttyUSB1", 1_000_000, 1)
    assert parse_servo_uri("pty:///tmp/x/servo?id=7").dxl_id == 7
    assert parse_servo_uri("/dev/ttyUSB0").baud == 1_000_000


@pytest.mark.parametrize("uri", ["udp://host:1", "serial:///dev/x?baud=400000",
                                 "serial:///dev/x?id=254", "serial:///dev/x?speed=1",
                                 "serial:///dev/x?id=one", "serial://"])
def test_that_bad_uris_are_refused_naming_the_uri(uri: str) -> None:
    with pytest.raises(TransportUriError) as err:
        parse_servo_uri(uri)
    assert err.value.device == uri


def test_that_35_deg_of_tilt_is_7964_steps_through_the_20_to_1_worm() -> None:
    assert tilt_to_steps(math.radians(35.0), 0.05, 0) == 7964
    assert tilt_to_steps(math.radians(35.0), 0.05, -1000) == 6964
    # One step is 0.0044 deg of tilt.
    assert math.degrees(steps_to_tilt(1, 0.05, 0)) == pytest.approx(0.0044, abs=1e-4)


@given(st.floats(0.0, math.radians(35.0)), st.integers(-20000, 20000))
def test_that_tilt_to_steps_and_back_is_within_half_a_step(tilt: float, zero: int) -> None:
    back = steps_to_tilt(tilt_to_steps(tilt, 0.05, zero), 0.05, zero)
    assert abs(back - tilt) <= 0.5 * math.radians(360.0 / 4096) * 0.05 + 1e-12


@given(st.floats(-1.0, 1.0), st.floats(-10.0, 10.0), st.floats(0.0, 0.5))
def test_that_the_goal_stays_in_range_and_never_moves_faster_than_the_rate(
        previous: float, requested: float, dt: float) -> None:
    max_tilt, rate = math.radians(35.0), math.radians(10.0)
    previous = min(max(previous, 0.0), max_tilt)
    goal = rate_limited_goal(previous, requested, max_tilt, rate, dt)
    assert 0.0 <= goal <= max_tilt
    assert abs(goal - previous) <= rate * dt + 1e-12
    if abs(min(max(requested, 0.0), max_tilt) - previous) <= rate * dt:
        assert goal == pytest.approx(min(max(requested, 0.0), max_tilt))


def test_that_a_config_file_is_validated_before_any_port_opens() -> None:
    text = "schema: tilt-servo\nversion: 1\nuri: serial:///dev/ttyUSB1?baud=1000000&id=1\n" \
           "rate_hz: 100\n"
    cfg = load_config_text(text, TiltServoConfig, schema="tilt-servo")
    assert cfg.rate_hz == 100.0 and cfg.gear_ratio == 0.05
    with pytest.raises(ConfigError, match="zero_offset_steps"):
        load_config_text("schema: tilt-servo\nversion: 1\nzero_offset_steps: 25000\n",
                         TiltServoConfig, schema="tilt-servo")
    with pytest.raises(ConfigError, match="rate_hz"):
        load_config_text("schema: tilt-servo\nversion: 1\nrate_hz: 1000\n",
                         TiltServoConfig, schema="tilt-servo")


def test_that_set_tilt_clamps_and_refuses_a_non_finite_goal() -> None:
    servo = TiltServo(TiltServoConfig(uri="/dev/null-servo"))
    servo.set_tilt(math.radians(50.0))
    assert servo._mailbox.goal[0] == pytest.approx(math.radians(35.0))
    servo.set_tilt(-1.0)
    assert servo._mailbox.goal[0] == 0.0
    with pytest.raises(ValueError, match="null-servo"):
        servo.set_tilt(math.nan)


def test_that_an_unstarted_servo_reports_not_started_with_no_measurement() -> None:
    state = TiltServo(TiltServoConfig(uri="/dev/null-servo")).latest()
    assert state.health.name == "NOT_STARTED"
    assert math.isnan(state.tilt_rad) and state.age_s == math.inf


def test_that_the_mailbox_never_hands_out_a_half_written_state() -> None:
    # Fixture: another process publishes states whose slots all hold the same number.
    ctx = mp.get_context("spawn")
    mailbox = _Mailbox(ctx)
    done = ctx.Event()
    writer = ctx.Process(target=hammer_mailbox, args=(mailbox, 200_000, done), daemon=True)
    writer.start()
    # Test: snapshot as fast as possible while it writes.
    seen, last = 0, None
    try:
        deadline = time.monotonic() + 120.0
        while (not done.is_set() or seen == 0) and writer.exitcode is None \
                and time.monotonic() < deadline:
            snap = mailbox.snapshot(last)
            if snap is not None and snap[_S.SEQLOCK] > 0:  # 0: nothing published yet
                # Assert: every snapshot is one whole publication.
                assert len(set(snap[1:])) == 1, snap
                last = snap
                seen += 1
    finally:
        writer.join(30.0)
    assert seen > 0 and writer.exitcode == 0


def test_that_the_error_byte_reads_as_words() -> None:
    assert error_names(ErrorBit.NONE) == "none"
    assert error_names(ErrorBit.OVERLOAD | ErrorBit.VOLTAGE) == "voltage, overload"
    assert error_names(ErrorBit(0x84)) == "overheating, 0x80"  # a bit the MX-28 never sets
