"""Scheduled faults of the simulated vehicle: ``KIND@T[:VALUE[:ROTOR]]``, one parser for all.

The emulated backend (``python -m sim_backend.backend --fault ...``, a session's
``backend.faults``) and the scenario layer (:mod:`sim_backend.scenario`, which ``fasthex
simulate`` flies in-process too) read the same text with :meth:`ScheduledFault.parse`; what a
kind does is implemented once per way of flying (the byte-path devices in
:mod:`sim_backend.backend`, the in-process sensors in :mod:`sim_backend.scenario`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

FaultKind = Literal["mocap-dropout", "fc-disconnect", "servo-silent", "battery-sag",
                    "tilt-kick", "imu-rate", "imu-gap", "mocap-jump", "rotor-thrust",
                    "mocap-freeze", "mocap-latency"]

FAULT_KINDS = ("mocap-dropout", "fc-disconnect", "servo-silent", "battery-sag", "tilt-kick",
               "imu-rate", "imu-gap", "mocap-jump", "rotor-thrust", "mocap-freeze",
               "mocap-latency")
#: a tilt kick acts over this time, in this many equal steps of the body rate
TILT_KICK_S = 0.05
TILT_KICK_STEPS = 25
#: kinds whose VALUE may be negative (a direction)
SIGNED_FAULT_KINDS = ("tilt-kick", "mocap-jump")
#: the estimator's pose history is about this long: a later pose cannot be fused anyway
MAX_MOCAP_LATENCY_S = 0.5
N_ROTORS = 6


@dataclass(frozen=True)
class ScheduledFault:
    """A fault to inject at a simulated time: ``kind@T`` or ``kind@T:VALUE`` (T in seconds).

    Kinds and their VALUE:

    - ``mocap-dropout@T:SECONDS``: the markers are occluded for that long;
    - ``fc-disconnect@T``: the Flight-Ctrl cable is pulled;
    - ``servo-silent@T``: the servo stops answering (the tilt stays where it is);
    - ``battery-sag@T:VOLTS``: from T on the pack reads VOLTS lower (a failing cell);
    - ``tilt-kick@T:DEG_S``: from T the body's roll rate is pushed up by DEG_S within
      ``TILT_KICK_S`` (an impulsive torque, as from a blow to an arm);
    - ``imu-rate@T:FRACTION``: from T on only FRACTION of the IMU samples reach the host (the
      others are lost on the wire, spread evenly: a degraded link);
    - ``imu-gap@T:SECONDS``: every IMU sample of that span is lost on the wire;
    - ``mocap-jump@T:METRES``: from T on the MoCap reports the body that far off along world x
      (a marker swap, a recalibrated room);
    - ``rotor-thrust@T:SCALE``: from T on every rotor's thrust is SCALE times what it was
      (0: propellers off, or rotors that cannot lift); ``rotor-thrust@T:SCALE:ROTOR`` only
      rotor ROTOR (1..6): a weakened (0.7) or lost (0) rotor;
    - ``mocap-freeze@T``: from T on the MoCap keeps reporting the pose it had at T (a frozen
      tracker that still streams);
    - ``mocap-latency@T:SECONDS``: from T on the MoCap frames arrive SECONDS after capture (a
      latency step: a loaded tracker PC, a congested network).
    """

    kind: FaultKind
    t_s: float
    duration_s: float = 0.0
    """The VALUE: a duration (s) for ``mocap-dropout`` and ``imu-gap``, else the kind's unit."""
    rotor: int | None = None
    """``rotor-thrust`` only: the rotor (1..6) it applies to; ``None``: every rotor."""

    @property
    def value(self) -> float:
        return self.duration_s

    @property
    def end_s(self) -> float:
        """When the fault is over (the start for the kinds that last)."""
        return self.t_s + (self.duration_s if self.kind in ("mocap-dropout", "imu-gap")
                           else 0.0)

    @classmethod
    def parse(cls, text: str) -> ScheduledFault:
        kind, _, when = text.partition("@")
        t, _, rest = when.partition(":")
        dur, _, rotor_text = rest.partition(":")
        if kind not in FAULT_KINDS or not t:
            raise ValueError(f"fault {text!r}: expected KIND@T[:VALUE] with KIND one of "
                             f"{', '.join(FAULT_KINDS)}")
        try:
            t_s, dur_s = float(t), float(dur) if dur else 0.0
        except ValueError:
            raise ValueError(f"fault {text!r}: T and VALUE are numbers") from None
        if not (math.isfinite(t_s) and math.isfinite(dur_s)):
            raise ValueError(f"fault {text!r}: T and VALUE must be finite")
        if t_s < 0.0 or (dur_s < 0.0 and kind not in SIGNED_FAULT_KINDS):
            raise ValueError(f"fault {text!r}: times must be >= 0")
        if kind == "imu-rate" and not 0.0 <= dur_s <= 1.0:
            raise ValueError(f"fault {text!r}: FRACTION of the IMU samples in [0, 1]")
        if kind == "rotor-thrust" and not 0.0 <= dur_s <= 2.0:
            raise ValueError(f"fault {text!r}: SCALE of the rotors' thrust in [0, 2]")
        if kind == "mocap-latency" and dur_s > MAX_MOCAP_LATENCY_S:
            raise ValueError(f"fault {text!r}: a MoCap latency of at most "
                             f"{MAX_MOCAP_LATENCY_S:g} s")
        if kind in ("battery-sag", "imu-rate", "mocap-jump", "tilt-kick", "rotor-thrust",
                    "mocap-latency") and not dur:
            raise ValueError(f"fault {text!r}: {kind} needs a VALUE ({kind}@T:VALUE)")
        rotor: int | None = None
        if rotor_text:
            if kind != "rotor-thrust":
                raise ValueError(f"fault {text!r}: only rotor-thrust takes a third field "
                                 "(the rotor)")
            if not rotor_text.isdigit() or not 1 <= int(rotor_text) <= N_ROTORS:
                raise ValueError(f"fault {text!r}: ROTOR is one of 1..{N_ROTORS}")
            rotor = int(rotor_text)
        return cls(kind, t_s, dur_s, rotor)  # type: ignore[arg-type]


class ImuWireLoss:
    """Which IMU samples the scheduled faults lose on the wire (the emulated board's
    ``imu_wire_fault`` hook, called with each sample's index and simulated time)."""

    def __init__(self, faults: Sequence[ScheduledFault]) -> None:
        self.gaps = [(f.t_s, f.t_s + f.value) for f in faults if f.kind == "imu-gap"]
        rates = [(f.t_s, f.value) for f in faults if f.kind == "imu-rate"]
        self.rate = min(rates) if rates else None  # (from, fraction kept)
        self._first: int | None = None

    def __call__(self, index: int, t_s: float) -> bool:
        t = t_s + 1e-9  # the sample times are whole nanoseconds
        if any(a <= t < b for a, b in self.gaps):
            return True
        if self.rate is None or t < self.rate[0]:
            return False
        if self._first is None:
            self._first = index
        k, keep = index - self._first, self.rate[1]
        # Bresenham: sample k survives where floor(k keep) steps up, so any n successive
        # samples keep n * keep of them (+-1)
        return math.floor((k + 1) * keep + 1e-9) == math.floor(k * keep + 1e-9)
