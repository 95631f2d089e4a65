"""MikroKopter message codecs: unit conversions, lengths, and encode -> decode round trips."""

from __future__ import annotations

import contextlib
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.mikrokopter import messages as m

s16 = st.integers(-32768, 32767)
u8 = st.integers(0, 255)


def test_that_spin_rates_convert_to_the_reference_half_periods() -> None:
    cases = {100.0: 5000, -100.0: -5000, 80.0: 6250, 60.0: 8333, 16.0: 31250, 102.0: 4901,
             10.0: 32767, 0.0: 32767, -10.0: -32767, 15.2: 32767}
    for hz, period in cases.items():
        assert m.spin_hz_to_half_period(hz) == period, hz


def test_that_the_slowest_speed_threshold_is_one_over_65535_us() -> None:
    assert m.spin_hz_to_half_period(1e6 / 65535 * 0.9999) == 32767
    assert m.spin_hz_to_half_period(1e6 / 65535) == 32767  # 32767.5 truncated
    assert m.spin_hz_to_half_period(15.3) == 32679


def test_that_a_non_finite_spin_rate_is_refused() -> None:
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError):
            m.spin_hz_to_half_period(bad)


@given(st.floats(min_value=16.0, max_value=200.0))
def test_that_half_period_round_trip_loses_less_than_one_microsecond(hz: float) -> None:
    p = m.spin_hz_to_half_period(hz)
    back = m.half_period_to_spin_hz(p)
    # truncation toward 0 of p = 5e5/hz: back >= hz, and the error is below one µs of period
    assert back >= hz
    assert m.half_period_to_spin_hz(p + 1) < hz


def test_that_the_reference_imu_and_motor_messages_decode_to_si() -> None:
    imu = m.decode_board_message(bytes.fromhex("49 07 0000 0000 2652 000a ffec 001e"))
    assert imu == m.ImuMessage(7, (0.0, 0.0, 9.81), (0.01, -0.02, 0.03))
    motor = m.decode_board_message(bytes.fromhex("4d 09 22 1388 0190 05dc"))
    assert isinstance(motor, m.MotorMessage)
    assert (motor.motor_id, motor.spinning, motor.emergency) == (2, True, False)
    assert motor.speed_hz == pytest.approx(100.0)
    assert motor.throttle_pct == pytest.approx(39.1, abs=0.05)
    assert motor.current_a == pytest.approx(1.5)
    battery = m.decode_board_message(bytes.fromhex("42 01 41a0"))
    assert battery == m.BatteryMessage(1, pytest.approx(16.8))  # type: ignore[arg-type]


def test_that_a_wrong_length_is_rejected_like_the_laas_host_does() -> None:
    good = m.ImuMessage(1, (0.0, 0.0, 9.81), (0.0, 0.0, 0.0)).encode()
    for bad in (good[:-1], good + b"\x00"):
        with pytest.raises(m.MalformedMessageError, match="bad b'I' message"):
            m.decode_board_message(bad)
    with pytest.raises(m.MalformedMessageError):
        m.decode_board_message(b"Z\x00")


def test_that_a_motor_that_is_not_spinning_reads_zero_speed() -> None:
    motor = m.MotorMessage(0, 1, True, False, False, 5000, 0, 0.0)
    assert motor.speed_hz == 0.0


def test_that_imu_axes_map_board_to_body_and_back() -> None:
    axes = m.ImuAxes(axis=(1, 0, 2), sign=(1, -1, -1))
    board = (1.0, 2.0, 3.0)
    assert axes.to_body(board) == (2.0, -1.0, -3.0)
    assert axes.to_board(axes.to_body(board)) == board
    with pytest.raises(ValueError):
        m.ImuAxes(axis=(0, 0, 2))


def test_that_imu_calibration_gains_apply_to_their_own_sensor_only() -> None:
    axes = m.ImuAxes(axis=(0, 1, 2), sign=(1, -1, -1), accel_gain=1.02, gyro_gain=0.98)
    msg = m.ImuMessage(0, (0.0, 0.0, -9.62), (0.1, 0.0, 0.0))
    accel, gyro = axes.imu_to_body(msg)
    assert accel == pytest.approx((0.0, 0.0, 9.8124))
    assert gyro == pytest.approx((0.098, 0.0, 0.0))
    back = axes.imu_to_board(accel, gyro)
    assert back[0] == pytest.approx(msg.accel_m_s2) and back[1] == pytest.approx(msg.gyro_rad_s)


vec_raw = st.tuples(s16, s16, s16)


@st.composite
def board_messages(draw: st.DrawFn) -> m.BoardMessage:
    kind = draw(st.sampled_from("ICMBT?N"))
    if kind == "I":
        a, g = draw(vec_raw), draw(vec_raw)
        return m.ImuMessage(draw(u8), (a[0] * 1e-3, a[1] * 1e-3, a[2] * 1e-3),
                            (g[0] * 1e-3, g[1] * 1e-3, g[2] * 1e-3))
    if kind == "C":
        f = draw(vec_raw)
        return m.MagMessage(draw(u8), (f[0] * 1e-8, f[1] * 1e-8, f[2] * 1e-8))
    if kind == "M":
        return m.MotorMessage(draw(u8), draw(st.integers(0, 15)), draw(st.booleans()),
                              draw(st.booleans()), draw(st.booleans()), draw(s16), draw(s16),
                              draw(st.integers(0, 65535)) * 1e-3)
    if kind == "B":
        return m.BatteryMessage(draw(u8), draw(st.integers(0, 65535)) * 1e-3)
    if kind == "T":
        return m.ClockRateMessage(draw(u8), draw(u8))
    text = draw(st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126),
                        max_size=40))
    return m.IdentityMessage(text) if kind == "?" else m.TextMessage(b"N", text)


@given(board_messages())
def test_that_every_board_message_round_trips(msg: m.BoardMessage) -> None:
    wire = msg.encode()
    assert m.decode_board_message(wire) == msg
    assert m.decode_board_message(wire).encode() == wire


@st.composite
def host_messages(draw: st.DrawFn) -> m.HostMessage:
    kind = draw(st.sampled_from("?sgxwq~"))
    n = draw(st.integers(1, 8))
    if kind == "?":
        return m.Identify()
    if kind == "s":
        return m.SetStreamPeriod(draw(st.sampled_from(list(m.Stream))),
                                 draw(st.integers(0, 2**32 - 1)))
    if kind in "gx":
        motor = draw(st.none() | u8)
        return m.StartMotors(motor) if kind == "g" else m.StopMotors(motor)
    if kind == "w":
        return m.SpinRates(tuple(draw(st.lists(s16, min_size=n, max_size=n))))
    if kind == "q":
        return m.Throttles(tuple(draw(st.lists(s16, min_size=n, max_size=n))))
    return m.Beep(draw(st.integers(0, 65535)))


@given(host_messages())
def test_that_every_host_message_round_trips(msg: m.HostMessage) -> None:
    assert m.decode_host_message(msg.encode()) == msg


@given(st.lists(st.floats(min_value=-200.0, max_value=200.0), min_size=6, max_size=6))
def test_that_spin_rates_from_hz_survive_the_wire(speeds: list[float]) -> None:
    msg = m.SpinRates.from_hz(speeds)
    back = m.decode_host_message(msg.encode())
    assert back == msg


@st.composite
def stock_messages(draw: st.DrawFn) -> m.StockMessage:
    kind = draw(st.sampled_from("vVdDcCbBtT"))
    if kind == "v":
        return m.VersionRequest()
    if kind == "V":
        b = draw(st.lists(u8, min_size=10, max_size=10))
        return m.VersionInfo(b[0], b[1], b[2], b[3], b[4], (b[5], b[6]), b[7], b[8], b[9])
    if kind == "d":
        return m.DebugRequest(draw(u8) * 10)
    if kind == "D":
        return m.DebugOut((draw(u8), draw(u8)),
                          tuple(draw(st.lists(s16, min_size=32, max_size=32))))
    if kind == "c":
        return m.Data3DRequest(draw(u8) * 10)
    if kind == "C":
        a = draw(vec_raw)
        s8 = st.integers(-128, 127)
        return m.Data3D((a[0] * 0.1, a[1] * 0.1, a[2] * 0.1), (draw(s8), draw(s8), draw(s8)),
                        draw(st.integers(0, 65535)))
    if kind == "b":
        s8 = st.integers(-128, 127)
        return m.ExternControl(draw(s8), draw(s8), draw(s8), draw(s8), draw(u8), draw(u8))
    if kind == "B":
        return m.ExternControlAck(draw(u8))
    if kind == "t":
        size = draw(st.sampled_from([4, 16]))
        return m.EngineTest(tuple(draw(st.lists(u8, min_size=size, max_size=size))))
    return m.EngineTestAck()


@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6,
                          max_value=1e6), min_size=1, max_size=8),
       st.lists(st.sampled_from((1, -1)), min_size=8, max_size=8))
def test_that_the_fast_w_encoder_gives_the_spin_rates_message_bytes(
        speeds: list[float], directions: list[int]) -> None:
    dirs = directions[:len(speeds)]
    expected = m.SpinRates.from_hz([d * abs(s) for d, s in zip(dirs, speeds, strict=True)])
    assert m.encode_spin_rates_hz(speeds, dirs) == expected.encode()


def test_that_the_fast_w_encoder_agrees_at_the_edges_of_its_inline_range() -> None:
    # the inline conversion covers [MIN_SPIN_HZ, 500 kHz]; each edge, just inside and just
    # outside, both directions, and zero with either sign
    edges = [m.MIN_SPIN_HZ, 500_000.0, 0.0, -0.0, 1e6, 16.0, 1.0]
    speeds = [x for e in edges for x in (e, math.nextafter(e, math.inf),
                                          math.nextafter(e, -math.inf))]
    for d in (1, -1):
        for s in speeds:
            expected = m.SpinRates.from_hz([d * abs(s)]).encode()
            assert m.encode_spin_rates_hz([s], [d]) == expected, (s, d)


def test_that_the_fast_w_encoder_refuses_a_non_finite_rate_and_a_length_mismatch() -> None:
    with pytest.raises(ValueError, match="not finite"):
        m.encode_spin_rates_hz([80.0, math.nan], [1, -1])
    with pytest.raises(ValueError):
        m.encode_spin_rates_hz([80.0, 80.0, 80.0], [1, -1])


@given(stock_messages())
def test_that_every_stock_message_round_trips_through_the_framing(msg: m.StockMessage) -> None:
    from drivers.mikrokopter import framing_stock as mk

    wire = mk.encode_frame(mk.Address.FLIGHT_CTRL, msg.CMD, msg.payload())
    (frame,) = mk.StockParser().feed(wire)
    assert m.decode_stock_message(frame.cmd, frame.data) == msg


@given(st.binary(max_size=70))
def test_that_random_messages_decode_or_raise_only_malformed(data: bytes) -> None:
    for decode in (m.decode_board_message, m.decode_host_message):
        with contextlib.suppress(m.MalformedMessageError):
            decode(data)
    with contextlib.suppress(m.MalformedMessageError):
        m.decode_stock_message(data[:1], data[1:])
