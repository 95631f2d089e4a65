"""A flight session's MAVLink ground-control link: keys, commands to the loop, the stats file.

The bridge (:mod:`groundstation.mavlink_bridge`) runs in the session's telemetry process. This
module is the wiring between it and the session:

Signing key (secure by default)
    The first of these that is given turns signing on (:func:`resolve_key`):

    1. ``fasthex fly --mavlink-key-file PATH``;
    2. the session's ``telemetry.mavlink_key_file`` (a path; the key itself never goes into
       YAML), absolute, ``~``-relative or relative to the working directory;
    3. the ``FASTHEX_MAVLINK_KEY`` environment variable.

    A file holds 64 hex digits, a passphrase (its SHA-256 is the key, as in MAVProxy's
    ``signing key PASSPHRASE``) or 32 raw bytes. A named file that is missing, unreadable or
    empty is an error before anything opens (:class:`MavlinkKeyError`, exit 2). With a key,
    unsigned, wrongly signed, replayed and stale frames are rejected and counted. Without one,
    commands that change the flight are refused (MAV_RESULT_DENIED, counted) unless the
    session sets ``telemetry.mavlink_allow_unsigned: true``; then a warning event says so.

Commands
    :class:`LoopCommandSink` decides each command on the loop's latest published state
    (:func:`groundstation.operator.decide`) and queues the accepted ones for the loop as
    operator requests (arm, disarm, land, cut). The session flies its mission file, so
    take-off, tilt, setpoints and parameters are answered UNSUPPORTED.

End of the session
    :meth:`SessionGcs.close` publishes the final state (DISARMED or CUT), announces it for
    :data:`FINAL_ANNOUNCE_S` (HEARTBEAT disarmed, EXTENDED_SYS_STATE ON_GROUND, one
    STATUSTEXT), then writes the bridge's counters to ``<record>.mavlink.json`` next to the
    flight record, which ``fasthex fly`` reads into its summary and ``--json``
    (:func:`summary_fields`: ``mavlink_rejected_unsigned``, ``mavlink_rejected_bad_signature``,
    ``mavlink_rejected_replay``, ``mavlink_rejected_stale``, ``mavlink_refused_unsigned``,
    ``mavlink_refused_out_of_range``, ...). A file rather than shared memory: the telemetry
    process writes it once, after its last frame, and it stays with the record.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import DriverError
from drivers.mavlink.config import MavlinkConfig
from drivers.mavlink.signing import DEFAULT_KEY_ENV, SigningKeyError, load_signing_key
from groundstation import operator as op
from groundstation.cli import UserError
from groundstation.operator import STATUS_BATTERY, STATUS_PREFLIGHT, STATUS_STATE

log = logging.getLogger(__name__)

#: How long the final state is repeated before the telemetry process exits (s, wall time).
FINAL_ANNOUNCE_S = 1.5
STATS_SUFFIX = ".mavlink.json"



class MavlinkKeyError(UserError):
    """The configured signing key cannot be used (printed as one line, exit 2)."""


@dataclass(frozen=True)
class GcsOptions:
    """What the telemetry process needs to run the link (picklable)."""

    uri: str
    key: bytes | None  # None: unsigned link
    key_source: str  # "--mavlink-key-file FILE", "telemetry.mavlink_key_file FILE", "$VAR", ""
    allow_unsigned: bool  # flight-changing commands accepted without a key
    stats_path: str  # where the counters go at the end ("" for nowhere)
    final_announce_s: float = FINAL_ANNOUNCE_S

    def __repr__(self) -> str:  # never print the key
        return (f"GcsOptions(uri={self.uri!r}, signed={self.key is not None}, "
                f"key_source={self.key_source!r}, allow_unsigned={self.allow_unsigned})")


def resolve_key(cli_key_file: str | None, session_key_file: str | None,
                environ: Mapping[str, str] | None = None) -> tuple[bytes | None, str]:
    """The signing key and where it came from: CLI file > session file > environment.

    Raises :class:`MavlinkKeyError` naming the file (or variable) when it cannot be used."""
    env = os.environ if environ is None else environ
    for label, path in (("--mavlink-key-file", cli_key_file),
                        ("telemetry.mavlink_key_file", session_key_file)):
        if path:
            full = Path(path).expanduser()
            try:
                key = load_signing_key(full, None, env)
            except SigningKeyError as exc:
                raise MavlinkKeyError(f"{exc.device}: {exc.message} ({label})") from None
            if key is None:  # pragma: no cover - load_signing_key raises for a named file
                raise MavlinkKeyError(f"{full}: no signing key ({label})")
            return key, f"{label} {full}"
    try:
        key = load_signing_key(None, DEFAULT_KEY_ENV, env)
    except SigningKeyError as exc:
        raise MavlinkKeyError(f"{exc.device}: {exc.message}") from None
    return key, (f"${DEFAULT_KEY_ENV}" if key is not None else "")


def gcs_options(uri: str, telemetry: Any, record_path: Path, *,
                cli_key_file: str | None = None,
                environ: Mapping[str, str] | None = None) -> GcsOptions | None:
    """The link's options for a session (None when MAVLink is off). The key is resolved
    here, in the session's own process, so that a bad key file stops the session before any
    device opens; a key file named while MAVLink is off is still checked."""
    session_file = getattr(telemetry, "mavlink_key_file", None)
    if not uri:  # the files are still checked; the environment matters only with a link
        resolve_key(cli_key_file, session_file, {})
        return None
    key, source = resolve_key(cli_key_file, session_file, environ)
    return GcsOptions(uri=uri, key=key, key_source=source,
                      allow_unsigned=bool(getattr(telemetry, "mavlink_allow_unsigned", False)),
                      stats_path=str(stats_path(record_path)))


def stats_path(record_path: Path) -> Path:
    return record_path.with_suffix(record_path.suffix + STATS_SUFFIX)


class LoopCommandSink:
    """Decides MAVLink commands on the loop's latest state (``groundstation.operator.decide``)
    and forwards the accepted ones to the loop as operator requests."""

    def __init__(self, status: Any, commands: Any, max_tilt_rad: float) -> None:
        self.status, self.commands, self.max_tilt_rad = status, commands, max_tilt_rad

    def submit(self, cmd: op.OperatorCommand) -> op.CommandResult:
        phase = _phase(self.status)
        if phase in (op.FlightPhase.DISARMED, op.FlightPhase.CUT) and \
                not isinstance(cmd, op.EmergencyStop | op.Disarm):
            # a fly session flies once: over (or its motors cut), nothing re-arms or lands it,
            # now or on a retry (the generic table's ACCEPTED / TEMPORARILY_REJECTED there
            # would promise what this session cannot do)
            return op.CommandResult.DENIED
        result = op.decide(cmd, phase, preflight_ok=bool(self.status[STATUS_PREFLIGHT]),
                           max_tilt_rad=self.max_tilt_rad)
        if phase is op.FlightPhase.ARMED and isinstance(cmd, op.Arm):
            return result  # already armed: acknowledged, no request (the loop would refuse it)
        request = {op.Arm: "arm", op.Disarm: "disarm", op.Land: "land",
                   op.EmergencyStop: "cut"}.get(type(cmd))
        if result is op.CommandResult.ACCEPTED:
            if request is None:  # the session flies its mission file: no takeoff/setpoints
                return op.CommandResult.UNSUPPORTED
            try:
                self.commands.put_nowait(request)
            except queue.Full:
                return op.CommandResult.TEMPORARILY_REJECTED
        return result


def _phase(status: Any) -> op.FlightPhase:
    try:
        return op.FlightPhase(int(status[STATUS_STATE]))
    except (ValueError, OverflowError):  # not written yet (NaN) or garbage
        return op.FlightPhase.PREFLIGHT


def vehicle_telemetry(row: Any, status: Any, events: list[str],
                      phase: op.FlightPhase | None = None) -> op.VehicleTelemetry:
    """One record row and the loop's status block -> a snapshot for the bridge (in ``phase``
    if given, else the status block's phase now)."""
    if phase is None:
        phase = _phase(status)

    def vec(v: Any) -> tuple[float, ...]:
        return tuple(float(x) for x in v)

    return op.VehicleTelemetry(
        t_s=float(row["t_s"]), phase=phase, armed=phase.armed,
        pos_w_m=vec(row["est_pos_w_m"]), vel_w_m_s=vec(row["vel_w_m_s"]),  # type: ignore[arg-type]
        q_wb=vec(row["est_q_wb"]), omega_b_rad_s=vec(row["omega_b_rad_s"]),  # type: ignore[arg-type]
        rotor_speeds_hz=vec(row["spin_hz"]), tilt_rad=float(row["alpha_rad"]),  # type: ignore[arg-type]
        battery_v=float(status[STATUS_BATTERY]),
        health=op.SensorHealth(preflight_ok=bool(status[STATUS_PREFLIGHT])),
        events=tuple(status_event(e, float(row["t_s"])) for e in events),
    )


def status_event(line: str, t_default: float) -> op.StatusEvent:
    """``"T.TTT s TEXT"`` (or ``"FAULT T.TTT s: TEXT"``) -> a StatusEvent."""
    text = line.removeprefix("FAULT ")
    head, _, rest = text.partition(" s ")
    try:
        t_s = float(head)
    except ValueError:
        t_s, rest = t_default, text
    bad = line.startswith("FAULT") or "failsafe" in line or "lost" in line
    if " -> CUT" in line:
        severity = op.Severity.EMERGENCY
    elif bad or "unsigned" in line:
        severity = op.Severity.WARNING
    else:
        severity = op.Severity.INFO
    return op.StatusEvent(t_s, rest.lstrip(": ") if rest else text, severity)


class SessionGcs:
    """The bridge of one session, owned by the telemetry process."""

    def __init__(self, options: GcsOptions, params: Any, status: Any, commands: Any) -> None:
        from groundstation.mavlink_bridge import MavlinkBridge

        c = params.controller
        self.options = options
        self.status = status
        self._last_row: Any = None
        self._transitions_seen = 0  # phase changes of the status block published so far
        cfg = MavlinkConfig(uri=options.uri, signing=options.key is not None)
        self.bridge = MavlinkBridge(
            cfg, LoopCommandSink(status, commands, params.tilt.max_tilt_rad),
            params=op.operator_params(kp_pos=c.kp_pos, kv_pos=c.kv_pos, ki_pos=c.ki_pos,
                                      kr_att=c.kr_att, kw_att=c.kw_att,
                                      max_tilt_deg=params.tilt.max_tilt_deg,
                                      max_tilt_rate_deg_s=params.tilt.max_rate_deg_s),
            key=options.key, allow_unsigned_commands=options.allow_unsigned,
            # the loop's events carry every transition with its reason: no second copy
            phase_events=False, max_tilt_rad=params.tilt.max_tilt_rad)
        self.bridge.start()

    def notices(self) -> list[str]:
        """Lines for the events file about how the link is secured."""
        o = self.options
        if o.key is not None:
            return [f"mavlink {o.uri}: signed (key from {o.key_source}); unsigned, wrongly "
                    "signed, replayed and stale frames are rejected"]
        if o.allow_unsigned:
            return [f"mavlink {o.uri}: WARNING unsigned: commands from anyone on the network "
                    "are accepted (telemetry.mavlink_allow_unsigned is true)"]
        return [f"mavlink {o.uri}: unsigned, telemetry only: commands that change the flight "
                "are refused (set a key to command the vehicle)"]

    def publish(self, rows: Any, events: list[str]) -> None:
        """The rows the ring gave since the last call (oldest first, at least one) and the
        event lines: first each phase change since then, in order, at the row of its time
        (so a GCS sees a phase however briefly it lasted), then the newest row."""
        changes, self._transitions_seen = op.transitions_since(self.status,
                                                               self._transitions_seen)
        if changes:
            times = rows["t_s"]
            if self._last_row is None:
                # a first pass after the loop has moved on (a slow start of this process, a
                # fast lockstep flight): the bridge first learns the session's initial phase,
                # so that the first change is announced as one
                self.bridge.publish(vehicle_telemetry(rows[0], self.status, [],
                                                      op.FlightPhase.PREFLIGHT))
            for t_s, phase in changes:
                i = min(max(int(np.searchsorted(times, t_s, side="right")) - 1, 0),
                        len(rows) - 1)
                self.bridge.publish(vehicle_telemetry(rows[i], self.status, [], phase))
        self._last_row = rows[-1]
        self.bridge.publish(vehicle_telemetry(rows[-1], self.status, events))

    def close(self, events: list[str] | None = None) -> None:
        """Final state out for ``final_announce_s``, the stats file written, link closed."""
        try:
            if self._last_row is not None:
                self.bridge.publish(vehicle_telemetry(self._last_row, self.status,
                                                      events or []))
            phase = _phase(self.status)
            self.bridge.announce_final(
                f"session over: {phase.name}, motors off",
                self.options.final_announce_s,
                severity=op.Severity.EMERGENCY if phase is op.FlightPhase.CUT
                else op.Severity.NOTICE)
        finally:
            self.bridge.close()
            if self.options.stats_path:
                with contextlib.suppress(OSError):
                    write_stats(Path(self.options.stats_path), self.bridge.stats(),
                                self.options)


def start_gcs(options: GcsOptions, params: Any, status: Any, commands: Any,
              events_path: str, echo_events: bool | Callable[[str], None]
              ) -> SessionGcs | None:
    """The telemetry process's link: bridge up and serving, its security notice in the
    events file (and to ``echo_events`` when it is a callable, on stderr when it is True). A
    link that cannot open (a udpin port in use) is one event line and no link: the flight
    record matters more."""
    gcs: SessionGcs | None = None
    try:
        gcs = SessionGcs(options, params, status, commands)
        lines = gcs.notices()
    except (DriverError, OSError) as exc:
        lines = [f"mavlink {options.uri}: WARNING no link: {exc}"]
    with open(events_path, "a", encoding="utf-8") as ev:
        for line in lines:
            ev.write(line + "\n")
            if gcs is not None:
                gcs.bridge.post_event(line, op.Severity.WARNING if "WARNING" in line
                                      else op.Severity.INFO)
            if callable(echo_events):
                echo_events(line)
            elif echo_events:
                with contextlib.suppress(OSError):
                    print(line, file=sys.stderr, flush=True)
    return gcs


def write_stats(path: Path, stats: Any, options: GcsOptions) -> None:
    s = stats.signing
    out = {
        "signed": options.key is not None,
        "key_source": options.key_source,
        "allow_unsigned": options.allow_unsigned,
        "frames_in": stats.frames_in,
        "corrupted_in": stats.corrupted_in,
        "frames_out": sum(stats.messages_out.values()),
        "signed_good": s.good if s else 0,
        "rejected_unsigned": s.unsigned_rejected if s else 0,
        "rejected_bad_signature": s.bad_signature if s else 0,
        "rejected_replay": s.replayed if s else 0,
        "rejected_stale": s.stale if s else 0,
        "refused_unsigned": stats.refused_unsigned,
        "refused_out_of_range": stats.refused_out_of_range,
        "handler_errors": stats.handler_errors,
        "commands": dict(stats.command_results),
        "setpoints": dict(stats.setpoint_results),
        "messages_out": dict(stats.messages_out),
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def read_stats(record_path: Path) -> dict[str, Any] | None:
    """The counters a session's link left next to its record; None without a link."""
    try:
        data = json.loads(stats_path(record_path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def summary_fields(record_path: Path) -> dict[str, Any]:
    """``mavlink_*`` keys for ``fasthex fly``'s summary (empty when MAVLink was off)."""
    stats = read_stats(record_path)
    if stats is None:
        return {}
    keys = ("signed", "allow_unsigned", "frames_in", "corrupted_in", "frames_out",
            "signed_good", "rejected_unsigned", "rejected_bad_signature", "rejected_replay",
            "rejected_stale", "refused_unsigned", "refused_out_of_range", "handler_errors")
    out: dict[str, Any] = {f"mavlink_{k}": stats.get(k, 0) for k in keys}
    out["mavlink_commands"] = stats.get("commands", {})
    return out


def summary_lines(record_path: Path) -> list[str]:
    """The human-readable MAVLink line(s) of the exit summary (none when it was off)."""
    f = summary_fields(record_path)
    if not f:
        return []
    mode = "signed" if f["mavlink_signed"] else (
        "unsigned, commands allowed" if f["mavlink_allow_unsigned"] else "unsigned, telemetry only")
    return [f"mavlink ({mode}): {f['mavlink_frames_in']} frames in, {f['mavlink_frames_out']} out;"
            f" rejected: unsigned {f['mavlink_rejected_unsigned']}, bad signature "
            f"{f['mavlink_rejected_bad_signature']}, replay {f['mavlink_rejected_replay']}, "
            f"stale {f['mavlink_rejected_stale']}; refused: unsigned commands "
            f"{f['mavlink_refused_unsigned']}, out of range {f['mavlink_refused_out_of_range']}"]
