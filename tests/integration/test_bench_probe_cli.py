"""``fasthex probe`` on a bench where nothing is plugged in: one line per device, no traceback."""

from __future__ import annotations

import subprocess
import sys

from config import find_config


def test_that_probe_of_absent_hardware_prints_one_line_per_device() -> None:
    # Test: the hardware template's placeholder ports and TEST-NET MoCap address
    proc = subprocess.run([sys.executable, "-m", "groundstation", "probe",
                           str(find_config("sessions", "hardware-template"))],
                          capture_output=True, text=True, timeout=120)
    lines = proc.stdout.splitlines()
    # Assert
    assert proc.returncode == 1
    assert "Traceback" not in proc.stdout + proc.stderr
    assert [line.split()[0] for line in lines] == ["flight-ctrl", "servo", "mocap"]
    assert lines[0] == ("flight-ctrl  serial:///dev/ttyUSB0?baud=500000: NOT FOUND: no such "
                        "device: is the adapter plugged in and powered? (`ls -l "
                        "/dev/serial/by-id/` lists the USB-serial adapters)")
    assert lines[1].endswith("?baud=1000000&id=1: NOT FOUND: no such device: is the adapter "
                             "plugged in and powered? (`ls -l /dev/serial/by-id/` lists the "
                             "USB-serial adapters)")
    assert lines[2] == ("mocap        natnet://192.0.2.10?local=192.0.2.20&body=fasthex: NOT "
                        "FOUND: local address 192.0.2.20 is not an address of this host (the "
                        "URI's local= option; `ip -br addr` lists them)")


def test_that_servo_status_on_an_absent_port_is_one_line_exit_2() -> None:
    proc = subprocess.run([sys.executable, "-m", "groundstation", "servo", "status",
                           "--session", str(find_config("sessions", "hardware-template"))],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr == ("fasthex: serial:///dev/ttyUSB1?baud=1000000&id=1: no such device: "
                           "is the adapter plugged in and powered? (`ls -l /dev/serial/by-id/` "
                           "lists the USB-serial adapters)\n")
