"""The MoCap emulators' frame clock, and the lockstep backend's deferred captures: a frame sent
after a latency is captured once the emulated board's reply is on the wire, with the same bytes
as a capture made at its time."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from drivers.mikrokopter import framing_tk3
from drivers.mikrokopter import messages as mkm
from groundstation.configs import load_disturbances, load_vehicle
from sim_backend.backend import BackendOptions, EmulatedVehicleBackend
from sim_backend.emulators.schedule import CaptureSchedule


def _run(schedule: CaptureSchedule[int], latency_s: float, defer: bool, steps: int
         ) -> tuple[list[tuple[int, list[int]]], list[float]]:
    """Call the schedule every 2 ms, 10 ms frames; -> (per call: (captured, sent)), the times
    the captures ran at."""
    t = [0.0]
    ran: list[float] = []
    frames = iter(range(1000))

    def capture() -> int:
        ran.append(t[0])
        return next(frames)

    out = []
    for k in range(steps):
        t[0] = 0.002 * k
        captured, sent = schedule.due(t[0], latency_s, capture, defer)
        if defer:
            t[0] += 0.001  # after the board's reply: the vehicle has not moved on
            captured += schedule.capture_deferred()
        out.append((captured, sent))
    return out, ran


def test_that_deferred_captures_send_the_same_frames_at_the_same_calls() -> None:
    # Fixture: 100 Hz frames, 4 ms latency, one call per 2 ms step
    now, _ = _run(CaptureSchedule(0.01), 0.004, False, 40)
    # Test
    deferred, ran = _run(CaptureSchedule(0.01), 0.004, True, 40)
    # Assert: the same frames leave at the same calls; each capture ran after its step's call
    assert deferred == now
    assert sum(c for c, _ in now) == 8 and next(s for _, s in now if s) == [0]
    assert ran == pytest.approx([0.001 + 0.01 * i for i in range(8)])


def test_that_a_frame_without_latency_is_captured_at_once_even_when_deferral_is_asked() -> None:
    schedule: CaptureSchedule[str] = CaptureSchedule(0.01)
    # Test: with no latency the frame leaves in this very call, so it must exist now
    captured, sent = schedule.due(0.0, 0.0, lambda: "f0", defer=True)
    # Assert
    assert (captured, sent) == (1, ["f0"]) and schedule.capture_deferred() == 0


def test_that_a_deferred_capture_left_over_runs_before_the_next_captures() -> None:
    schedule: CaptureSchedule[str] = CaptureSchedule(0.01)
    calls: list[str] = []

    def capture(name: str) -> str:
        calls.append(name)
        return name

    # Test: no capture_deferred between the two calls
    assert schedule.due(0.0, 0.004, lambda: capture("a"), defer=True) == (0, [])
    assert schedule.next_event_s() == pytest.approx(0.004)  # the deferred frame's send time
    captured, sent = schedule.due(0.010, 0.004, lambda: capture("b"), defer=True)
    # Assert: nothing lost, in capture order; the first frame's send time has passed
    assert (calls, captured, sent) == (["a"], 1, ["a"])
    assert schedule.capture_deferred() == 1 and calls == ["a", "b"]


def _backend(tmp_path: Path, name: str) -> EmulatedVehicleBackend:
    link = tmp_path / name
    link.mkdir()
    return EmulatedVehicleBackend(BackendOptions(
        vehicle=load_vehicle("fasthex"), preset=load_disturbances("paper-calibrated"),
        start_pos_w_m=(0.0, 0.0, 0.1), seed=3, clock="lockstep", link_dir=link))


def _fly(backend: EmulatedVehicleBackend, n_w: int) -> tuple[list[bytes], list[str]]:
    """Feed the board ``n_w`` spin-rate commands, as a lockstep ground station sends them;
    -> the NatNet packets sent, and the order of board writes and MoCap captures."""
    packets: list[bytes] = []
    events: list[str] = []
    mocap, fc = backend.mocap, backend.flight_ctrl
    send_frame, capture, write = mocap._send_frame, mocap._capture, fc._write

    def on_send(packet: bytes) -> None:
        packets.append(packet)
        send_frame(packet)

    def on_capture(t_s: float) -> bytes | None:
        events.append("capture")
        return capture(t_s)

    def on_write(data: bytes) -> None:
        events.append("write")
        write(data)

    mocap._send_frame = on_send  # type: ignore[method-assign]
    mocap._capture = on_capture  # type: ignore[method-assign]
    fc._write = on_write  # type: ignore[method-assign]
    fc.feed(framing_tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 2000).encode()))
    fc.feed(framing_tk3.encode_frame(mkm.StartMotors().encode()))
    for i in range(n_w):
        spins = [60.0 + 5.0 * math.sin(0.05 * i + k) for k in range(6)]
        fc.feed(framing_tk3.encode_frame(mkm.encode_spin_rates_hz(spins, (1, -1) * 3)))
    return packets, events


def test_that_the_lockstep_backend_captures_mocap_after_the_board_reply_with_the_same_bytes(
        tmp_path: Path) -> None:
    # Fixture: the paper-calibrated MoCap (100 Hz, noisy, with latency) on a lockstep backend,
    # and the same backend with its captures at the advance, as before deferral
    deferred, inline = _backend(tmp_path, "a"), _backend(tmp_path, "b")
    inline.vehicle.defer_captures = False
    assert deferred.vehicle.defer_captures and deferred.mocap.config.latency_s > 0.0
    try:
        # Test: 0.4 s of lockstep steps
        got, order = _fly(deferred, 200)
        want, order_inline = _fly(inline, 200)
    finally:
        deferred.stop()
        inline.stop()
    # Assert: bit-identical frames (pose noise, stamps, numbering), ~100 Hz of them
    assert got == want and len(got) == pytest.approx(40, abs=2)
    # every capture follows the board's write of its step (off the lockstep round trip), where
    # without deferral it precedes it
    assert "capture" in order and all(order[i - 1] == "write"
                                      for i, e in enumerate(order) if e == "capture")
    assert any(order_inline[i + 1] == "write" for i, e in enumerate(order_inline)
               if e == "capture")
    assert len(set(got)) == len(got)  # each frame a new capture


def test_that_a_failing_deferred_capture_is_logged_and_the_board_keeps_stepping(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # Fixture: the MoCap's capture fails once (a bug, a pose it cannot encode)
    backend = _backend(tmp_path, "a")
    capture = backend.mocap._capture
    calls = [0]

    def failing_once(t_s: float) -> bytes | None:
        calls[0] += 1
        if calls[0] == 2:
            raise RuntimeError("capture failed")
        return capture(t_s)

    backend.mocap._capture = failing_once  # type: ignore[method-assign]
    try:
        # Test
        packets, order = _fly(backend, 100)
    finally:
        backend.stop()
    # Assert: logged; every step still answered (one board write per w, plus the stream's
    # first sample), and the frames after the failed one still captured and sent
    assert "deferred work failed" in caplog.text
    assert order.count("write") == 101
    # (all but the failed one sent, bar the newest, which may still wait out its latency)
    assert len(packets) >= 15 and calls[0] - 1 - len(packets) in (0, 1)
