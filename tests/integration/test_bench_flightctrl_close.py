"""FlightCtrl.close() leaves a tk3 board as found: the exact bytes of the stop-and-streams-off
sequence (protocol reference §4.7 vectors), and nothing for a board that never spoke tk3."""

from __future__ import annotations

import threading
from pathlib import Path

from drivers.mikrokopter.device import FlightCtrl, FlightCtrlConfig
from sim_backend.ptylink import PtyEndpoint

STOP_ALL = bytes.fromhex("5e 78 24")  # x
STREAMS_OFF = b"".join(bytes([0x5E, cmd, 0, 0, 0, 0, 0x24]) for cmd in b"bmic")  # LAAS order
IDENTITY_REPLY = bytes.fromhex("5e 3f 6d 6b 66 6c 31 2e 38 24")  # ?mkfl1.8


def _board(pty: PtyEndpoint, received: bytearray, stop: threading.Event) -> None:
    """A minimal tk3 board: answers `?`, records everything else."""
    while not stop.is_set():
        if not pty.wait_readable(0.05):
            continue
        data = pty.read()
        received += data
        if b"^?$" in data:
            pty.write(IDENTITY_REPLY)


def test_that_close_sends_x_then_every_stream_period_zero(tmp_path: Path) -> None:
    # Fixture
    received = bytearray()
    stop = threading.Event()
    with PtyEndpoint(tmp_path / "flight-ctrl") as pty:
        board = threading.Thread(target=_board, args=(pty, received, stop), daemon=True)
        board.start()
        fc = FlightCtrl.open(f"pty://{pty.path}",
                             FlightCtrlConfig(identify_attempts=4, identify_timeout_s=2.0))
        try:
            ident = fc.identify()
        finally:
            stop.set()  # from here on only this thread reads the board's side
            board.join(5.0)
            # Test
            fc.close()
            fc.close()  # idempotent: the sequence goes out once
        after = bytearray()
        while pty.wait_readable(0.5):  # written before close() returned: all there
            after += pty.read()
    # Assert
    assert ident.firmware_id == "mkfl1.8"
    assert bytes(received) == b"^?$"
    assert bytes(after) == STOP_ALL + STREAMS_OFF


def test_that_a_silent_port_gets_no_tk3_bytes_on_close(tmp_path: Path) -> None:
    with PtyEndpoint(tmp_path / "silent") as pty:
        fc = FlightCtrl.open(f"pty://{pty.path}")
        fc.start()
        fc.close()
        assert not pty.wait_readable(0.2)
