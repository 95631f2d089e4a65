"""Serial realities at open: each failure is one line ``URI: what is wrong`` with the fix.

Real ptys where the situation can be made real (absent, already open by another process, a
regular file); the permission message from an injected errno on a real device node (root opens
a pty chmod'ed 000 anyway); the latency timer from a sysfs-shaped directory.
"""

from __future__ import annotations

import errno
import grp
import os
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.errors import DeviceOpenError
from drivers.transport import (
    _serial_open_error,
    check_latency_timer,
    describe_open_error,
    open_transport,
)
from sim_backend.ptylink import PtyEndpoint


def _one_line(exc: BaseException) -> str:
    text = str(exc)
    assert "\n" not in text
    return text


def test_that_an_absent_port_is_one_line_naming_the_uri(tmp_path: Path) -> None:
    missing = tmp_path / "ttyUSB9"
    for uri, hint in ((f"serial://{missing}?baud=500000", "is the adapter plugged in"),
                      (f"serial://{missing}?baud=0", "is the adapter plugged in"),
                      (f"pty://{missing}", "is the emulator (`fasthex emulate`) running")):
        with pytest.raises(DeviceOpenError) as info:
            open_transport(uri)
        text = _one_line(info.value)
        assert text.startswith(f"{uri}: no such ")
        assert hint in text
        assert info.value.errno == errno.ENOENT and info.value.device == str(missing)


@pytest.mark.parametrize("second", ["pty://{}", "serial://{}?baud=0",
                                    "serial://{}?baud=500000"])
def test_that_a_port_open_in_another_process_is_busy_naming_the_holder(
        second: str, tmp_path: Path) -> None:
    # Fixture: another process holds the port through the project's own transport
    with PtyEndpoint(tmp_path / "flight-ctrl") as pty:
        holder = subprocess.Popen(
            [sys.executable, "-c",
             "import sys; from drivers.transport import open_transport; "
             f"t = open_transport('pty://{pty.slave_path}'); print('open', flush=True); "
             "sys.stdin.read()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert holder.stdout is not None and holder.stdout.readline() == "open\n"
            # Test
            with pytest.raises(DeviceOpenError) as info:
                open_transport(second.format(pty.slave_path))
        finally:
            holder.communicate("", timeout=30)
        # Assert
        text = _one_line(info.value)
        assert "already open by another process" in text
        assert f"pid {holder.pid} (python" in text
        assert info.value.errno == errno.EBUSY
        # and once the holder has let go, the port opens again
        open_transport(f"pty://{pty.slave_path}").close()


def test_that_a_port_open_twice_in_one_process_is_refused(tmp_path: Path) -> None:
    with PtyEndpoint(tmp_path / "servo") as pty:
        first = open_transport(f"pty://{pty.slave_path}")
        try:
            with pytest.raises(DeviceOpenError, match="already open by this process"):
                open_transport(str(tmp_path / "servo"))  # the stable link, a bare path
        finally:
            first.close()


def test_that_permission_denied_names_the_group_and_the_fix(tmp_path: Path) -> None:
    # Fixture: a device node as udev makes it (crw-rw---- root:dialout), here a pty re-owned
    group = next((g for g in ("dialout", "uucp", "tty") if _has_group(g)), None)
    if group is None:
        pytest.skip("no dialout, uucp or tty group on this system")
    with PtyEndpoint() as pty:
        path = pty.slave_path
        st = os.stat(path)
        os.chown(path, 0, grp.getgrnam(group).gr_gid)
        os.chmod(path, 0o660)
        try:
            # Test: EACCES as a user outside the group gets it (root would open the node)
            text = describe_open_error(path, errno.EACCES)
        finally:
            os.chown(path, st.st_uid, st.st_gid)
            os.chmod(path, st.st_mode & 0o777)
    # Assert
    assert text == (f"permission denied: the device (crw-rw----) belongs to group {group!r}; "
                    f"add yourself with `sudo usermod -aG {group} $USER` and log in again")


def _has_group(name: str) -> bool:
    try:
        grp.getgrnam(name)
    except KeyError:
        return False
    return True


def test_that_a_baud_rate_the_adapter_refuses_is_a_clear_error(tmp_path: Path) -> None:
    # Fixture: what pyserial raises when the driver refuses the line speed
    with PtyEndpoint() as pty:
        exc = OSError(errno.EINVAL, "Invalid argument")
        refused = ValueError("Invalid baud rate: 3000000")
        # Test
        a = _serial_open_error(pty.slave_path, "serial://x?baud=3000000", 3_000_000, exc)
        b = _serial_open_error(pty.slave_path, "serial://x?baud=3000000", 3_000_000, refused)
    # Assert
    for err in (a, b):
        assert _one_line(err) == (
            "serial://x?baud=3000000: the adapter cannot run at 3000000 baud (the driver "
            "refused the line speed); tk3 boards run at 500000, stock ones at 57600")
        assert err.errno == errno.EINVAL


def test_that_a_latency_timer_above_1_ms_warns_with_the_command(tmp_path: Path) -> None:
    # Fixture: /sys/bus/usb-serial/devices/ttyUSB3/latency_timer at the FTDI default
    timer = tmp_path / "ttyUSB3" / "latency_timer"
    timer.parent.mkdir()
    timer.write_text("16\n")
    # Test
    value, warning = check_latency_timer("/dev/ttyUSB3", tmp_path)
    # Assert
    assert value == 16
    assert warning is not None and "latency timer is 16 ms" in warning
    assert f"echo 1 | sudo tee {timer}" in warning
    # lowered when writable (root, or a udev rule), then no warning
    assert check_latency_timer("/dev/ttyUSB3", tmp_path, lower=True) == (1, None)
    assert timer.read_text() == "1"
    # not a USB-serial port (an ACM modem, a pty): nothing to read
    assert check_latency_timer("/dev/ttyACM0", tmp_path) == (None, None)


def test_that_other_errnos_keep_the_os_reason() -> None:
    text = describe_open_error("/dev/ttyUSB0", errno.ELOOP, "too many links")
    assert text.startswith("cannot open: ") and "too many links" in text
    assert "nothing answers" in describe_open_error("/dev/ttyUSB0", errno.ENXIO)
