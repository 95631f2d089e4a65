"""Transports chosen by URI: schemes, options, typed errors naming the device, real ptys."""

from __future__ import annotations

import errno
import os
from collections.abc import Mapping
from pathlib import Path

import pytest

from drivers.errors import DeviceLostError, DeviceOpenError, TransportUriError
from drivers.transport import (
    TRANSPORTS,
    LoopTransport,
    SpyTransport,
    Transport,
    TransportFactory,
    TransportUri,
    open_transport,
    parse_uri,
)
from sim_backend.ptylink import PtyEndpoint


def _read_all(t: Transport, n: int) -> bytes:
    out = b""
    for _ in range(100):
        out += t.read(4096)
        if len(out) >= n:
            break
    return out


def test_that_uris_are_split_into_scheme_target_and_options() -> None:
    u = parse_uri("serial:///dev/ttyUSB0?baud=500000")
    assert (u.scheme, u.target, dict(u.options)) == ("serial", "/dev/ttyUSB0", {"baud": "500000"})
    assert parse_uri("/dev/ttyUSB0").scheme == "path"
    spy = parse_uri("spy://serial:///dev/x?baud=57600?log=out.txt")
    assert (spy.target, dict(spy.options)) == ("serial:///dev/x?baud=57600", {"log": "out.txt"})


def test_that_the_loopback_returns_what_was_written() -> None:
    t = open_transport("loop://")
    t.write(b"^?$")
    assert t.read(10) == b"^?$"
    assert t.read(10) == b""  # nothing more: the read timeout passes
    t.close()
    with pytest.raises(DeviceLostError):
        t.read(10)


def test_that_an_unknown_scheme_names_the_expected_forms() -> None:
    with pytest.raises(TransportUriError, match=r"unknown scheme 'tcp'.*serial://"):
        open_transport("tcp://host:1")


def test_that_an_unknown_option_names_the_expected_form() -> None:
    with pytest.raises(TransportUriError, match=r"unknown option 'parity'.*serial://<device>"):
        open_transport("serial:///dev/ttyUSB0?baud=500000&parity=E")
    with pytest.raises(TransportUriError, match="not an integer"):
        open_transport("serial:///dev/ttyUSB0?baud=fast")


def test_that_a_missing_port_raises_device_open_error_with_errno_and_device(
        tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyUSB9")
    for uri in (f"serial://{missing}?baud=500000", f"pty://{missing}", missing):
        with pytest.raises(DeviceOpenError) as info:
            open_transport(uri)
        assert info.value.device == missing
        assert info.value.errno == errno.ENOENT
        assert missing in str(info.value)


def test_that_a_regular_file_is_refused_as_not_a_tty(tmp_path: Path) -> None:
    path = tmp_path / "not-a-tty"
    path.write_bytes(b"")
    with pytest.raises(DeviceOpenError, match="not a tty"):
        open_transport(f"pty://{path}")


@pytest.mark.parametrize("form", ["pty://{}", "{}", "serial://{}?baud=0",
                                  "serial://{}?baud=500000&low_latency=1"])
def test_that_a_pty_carries_bytes_both_ways(form: str, tmp_path: Path) -> None:
    with PtyEndpoint(tmp_path / "flight-ctrl") as pty:
        t = open_transport(form.format(pty.path))
        try:
            t.write(b"^?$")
            assert pty.wait_readable(5.0)
            assert pty.read() == b"^?$"
            pty.write(b"\r\n\x00\xff^$")  # raw: no CR/LF translation
            assert _read_all(t, 6) == b"\r\n\x00\xff^$"
        finally:
            t.close()


def test_that_a_closed_pty_raises_device_lost_naming_the_device() -> None:
    pty = PtyEndpoint()
    t = open_transport(f"pty://{pty.slave_path}")
    pty.close()
    with pytest.raises(DeviceLostError) as info:
        for _ in range(100):
            t.read(16)
    assert info.value.device == pty.slave_path
    t.close()


def test_that_a_test_registry_adds_a_scheme_without_touching_the_default() -> None:
    made: list[str] = []

    def fake(uri: TransportUri, registry: Mapping[str, TransportFactory]) -> Transport:
        made.append(uri.target)
        return LoopTransport(uri.uri)

    registry = {**TRANSPORTS, "fake": fake}
    t = open_transport("fake://bench-3", registry=registry)
    assert made == ["bench-3"] and t.name == "fake://bench-3"
    assert "fake" not in TRANSPORTS
    with pytest.raises(TypeError):
        TRANSPORTS["fake"] = fake  # type: ignore[index]


def test_that_spy_logs_both_directions_to_a_file(tmp_path: Path) -> None:
    log = tmp_path / "spy.txt"
    t = open_transport(f"spy://loop://?log={log}")
    t.write(b"\x5e\x3f\x24")
    assert t.read(10) == b"^?$"
    t.close()
    lines = log.read_text().splitlines()
    assert [line.split(" ", 1)[1] for line in lines] == ["TX 5e 3f 24", "RX 5e 3f 24"]


def test_that_the_pty_transport_does_not_leak_descriptors() -> None:
    before = len(os.listdir("/proc/self/fd"))
    with PtyEndpoint() as pty:
        for _ in range(5):
            open_transport(f"pty://{pty.path}").close()
    assert len(os.listdir("/proc/self/fd")) == before


@pytest.mark.parametrize("through_spy", [False, True])
def test_that_a_read_timeout_given_per_call_overrides_the_transports_own(
        through_spy: bool) -> None:
    # Fixture: the transport's own read timeout is an hour; a call may ask for less
    with PtyEndpoint() as pty:
        t = open_transport(f"pty://{pty.path}")
        t.read_timeout_s = 3600.0  # type: ignore[attr-defined]
        if through_spy:
            t = SpyTransport(t, None)
        try:
            # Test / Assert: nothing waiting -> empty at once instead of after an hour
            assert t.read(4096, 0.0) == b""
            pty.write(b"^I$")
            got = b""
            for _ in range(100):
                got += t.read(4096, 5.0)
                if len(got) >= 3:
                    break
            assert got == b"^I$"
        finally:
            t.close()
