"""The live rerun dashboard of a flight, laid out like the paper's experiment figures.

Runs in the telemetry process (or ``fasthex replay``), never in the 500 Hz loop: each rerun call
costs 30-60 us of Python time and holds the GIL, so the loop only pushes flight-record rows into
a shared-memory ring and this module ships the drained blocks with ``send_columns`` (one call per
entity per block, ~100 ms of rows). Entry points::

    dash = Dashboard("save", "flight.rrd", metadata=record.metadata)
    dash.log_rows(rows)            # structured rows of groundstation.record.RECORD_DTYPE
    dash.log_event(t_s, "text")    # transitions, faults, preflight results
    dash.log_health(t_s, {"loop_jitter_p99_ms": 0.2, ...})
    dash.close()

Modes: ``spawn`` (native viewer; also saves when a path is given), ``serve`` (gRPC server on
127.0.0.1 and the web viewer, URL in :attr:`Dashboard.viewer_url`; also saves when a path is
given), ``save`` (a ``.rrd`` file only), ``off`` (nothing; rerun is not even imported).
:func:`default_mode` picks ``spawn`` with a display and ``save`` without.

Timelines: ``sim_time`` (the record's ``t_s``, a duration) and ``tick`` (row count, a sequence);
no wall-clock ``log_time``. Entities (:data:`PANEL_ENTITIES` lists the ones with data):

- ``/position/{ref,actual}`` [m], ``/position_error`` [mm: x, y, z, norm]
- ``/attitude/{ref,desired,actual}`` [deg: roll, pitch, yaw, ZYX], ``/attitude_error`` [deg]
- ``/spin/actual`` [Hz, six rotors], ``/spin/limits`` [Hz: min, max]
- ``/lateral_force`` [N: max r_xy, |u_f xy|], ``/tilt`` [deg: ref, cmd, actual]
- ``/actuation`` (0 UDT, 1 fully actuated, 2 MDT), ``/health/*`` (saturated rotors, caller
  values such as loop jitter and link loss), ``/events`` (text log)
- ``/world/vehicle`` (pose, body axes, arms, ``thrust`` arrows tilted by alpha and scaled by
  thrust), ``/world/reference`` (reference pose), ``/world/trail`` (last seconds of path)

Scalars go at full rate; poses at ``pose_every`` ticks, thrust arrows at ``arrows_every``
ticks and the trail at ``trail_every`` ticks (the 3-D view does not need 500 Hz).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import urllib.parse
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from groundstation.report import MDT, UDT, panel_signals

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

    from controller.params import VehicleParams

_log = logging.getLogger(__name__)

MODES = ("spawn", "serve", "save", "off")
APP_ID = "fasthex"
XYZ = ("x", "y", "z")
RPY = ("roll", "pitch", "yaw")

#: entity -> series names of every scalar panel
SCALAR_SERIES: dict[str, tuple[str, ...]] = {
    "/position/ref": tuple(f"{a} ref [m]" for a in XYZ),
    "/position/actual": tuple(f"{a} [m]" for a in XYZ),
    "/position_error": (*(f"e_{a} [mm]" for a in XYZ), "|e_p| [mm]"),
    "/attitude/ref": tuple(f"{a} ref [deg]" for a in RPY),
    "/attitude/desired": tuple(f"{a} desired [deg]" for a in RPY),
    "/attitude/actual": tuple(f"{a} [deg]" for a in RPY),
    "/attitude_error": tuple(f"e_{a} [deg]" for a in RPY),
    "/spin/actual": tuple(f"w{i} [Hz]" for i in range(1, 7)),
    "/spin/limits": ("min [Hz]", "max [Hz]"),
    "/lateral_force": ("max r_xy [N]", "|u_f xy| [N]"),
    "/tilt": ("alpha ref [deg]", "alpha cmd [deg]", "alpha [deg]"),
    "/actuation": ("state (0 UDT, 1 full, 2 MDT)",),
    "/health/saturated_rotors": ("saturated rotors",),
}
#: every entity a panel shows, all of which receive data from :meth:`Dashboard.log_rows`
PANEL_ENTITIES: tuple[str, ...] = (*SCALAR_SERIES, "/world/vehicle", "/world/vehicle/thrust",
                                   "/world/reference", "/world/trail")

_RGB = {"x": (230, 40, 40), "y": (40, 170, 40), "z": (40, 90, 230)}
_AXIS_RGB = [_RGB["x"], _RGB["y"], _RGB["z"]]
_AXIS_RGB_DIM = [(250, 150, 150), (150, 220, 150), (150, 170, 250)]
_ROTOR_RGB = [(255, 140, 0), (0, 170, 255), (255, 140, 0), (0, 170, 255), (255, 140, 0),
              (0, 170, 255)]  # CCW light orange, CW light blue as in the paper's sketch
#: a colour the viewer's own palette never uses: the browser test looks for it on screen
MARKER_RGB = (255, 0, 255)
_SERIES_COLORS: dict[str, list[tuple[int, int, int]]] = {
    "/position/ref": _AXIS_RGB_DIM, "/position/actual": _AXIS_RGB,
    "/position_error": [*_AXIS_RGB, (20, 20, 20)],
    "/attitude/ref": _AXIS_RGB_DIM, "/attitude/desired": [(180, 100, 100), (100, 160, 100),
                                                          (100, 120, 180)],
    "/attitude/actual": _AXIS_RGB, "/attitude_error": _AXIS_RGB,
    "/spin/actual": [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200),
                     (245, 130, 48), (145, 30, 180)],
    "/spin/limits": [(128, 128, 128), (128, 128, 128)],
    "/lateral_force": [(200, 200, 200), MARKER_RGB],
    "/tilt": [(200, 200, 200), (255, 165, 0), MARKER_RGB],
    "/actuation": [MARKER_RGB], "/health/saturated_rotors": [(255, 80, 80)],
}


_EVENT_RE = re.compile(r"^\s*([-+]?\d+(?:\.\d*)?)\s*s\s+(.*\S)\s*$")


def parse_events(text: str) -> list[tuple[float, str]]:
    """Events of a ``<record>.events.txt`` file, one ``"T.TTT s TEXT"`` line each, as
    (t_s, text). A line without a time stamp (``FAULT ...``, device banners) takes the time of
    the event before it (0 at the start); blank lines are skipped."""
    out: list[tuple[float, str]] = []
    t_prev = 0.0
    for line in text.splitlines():
        m = _EVENT_RE.match(line)
        if m:
            t = float(m.group(1))
            if math.isfinite(t):
                t_prev = t
                out.append((t, m.group(2)))
                continue
        if line.strip():
            out.append((t_prev, line.strip()))
    return out


def default_mode() -> str:
    """``spawn`` where a display is available, else ``save`` (headless machines)."""
    return "spawn" if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") else "save"


def blueprint() -> rrb.Blueprint:
    """The dashboard layout: 3-D view, events and health on the left; the paper's panels in two
    columns (position, position error, attitude, attitude error | spin rates, lateral force,
    tilt, actuation state)."""
    import rerun.blueprint as rrb

    def ts(name: str, origin: str, **kw: Any) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(name=name, origin=origin, **kw)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(name="vehicle", origin="/world"),
                rrb.TextLogView(name="events", origin="/events"),
                ts("health", "/health"),
                row_shares=[3, 2, 1]),
            rrb.Vertical(
                ts("1 position: reference vs actual [m]", "/position"),
                ts("2 position error [mm]", "/position_error"),
                ts("3-4 attitude: reference, desired, actual [deg]", "/attitude"),
                ts("5 attitude error [deg]", "/attitude_error")),
            rrb.Vertical(
                ts("6 spin rates and limits [Hz]", "/spin"),
                ts("7 lateral force: max vs actual [N]", "/lateral_force"),
                ts("8 tilt alpha: reference, command, actual [deg]", "/tilt"),
                ts("actuation: 0 UDT, 1 full, 2 MDT", "/actuation",
                   axis_y=rrb.ScalarAxis(range=(-0.2, 2.2)))),
            column_shares=[2, 3, 3]),
        rrb.TimePanel(timeline="sim_time", expanded=False),
        collapse_panels=True,
    )


def _xyzw(q_wxyz: npt.NDArray[Any]) -> npt.NDArray[np.float32]:
    q = np.asarray(q_wxyz, dtype=np.float32)
    return np.ascontiguousarray(np.concatenate([q[:, 1:4], q[:, :1]], axis=1))


def _level(text: str) -> str:
    t = text.lower()
    if any(w in t for w in ("fault", "fail", "cut", "e-stop", "estop", "lost", "error")):
        return "ERROR"
    if any(w in t for w in ("warn", "saturat", "land", "abort", "timeout", "stale")):
        return "WARN"
    return "INFO"


class Dashboard:
    """Ships flight-record rows, events and health values to rerun (see the module doc)."""

    def __init__(self, mode: str, rrd_path: str | Path | None = None, *,
                 metadata: Mapping[str, Any] | None = None,
                 params: VehicleParams | None = None, recording_id: str | None = None,
                 grpc_port: int = 9876, web_port: int = 9090,
                 server_memory_limit: str = "128MiB", pose_every: int = 5,
                 arrows_every: int = 25, trail_every: int = 50, trail_s: float = 10.0) -> None:
        if mode not in MODES:
            raise ValueError(f"dashboard mode must be one of {', '.join(MODES)}, not {mode!r}")
        if mode == "save" and rrd_path is None:
            raise ValueError("dashboard mode 'save' needs an .rrd path")
        self.mode = mode
        self.rrd_path = Path(rrd_path) if rrd_path is not None else None
        self.metadata = dict(metadata or {})
        self.viewer_url: str | None = None
        #: the error that switched the dashboard off, if any
        self.error: str | None = None
        self.grpc_url: str | None = None
        self.rows_logged = 0
        self._t_last = 0.0
        self.events_logged = 0
        self._pose_every = max(1, pose_every)
        self._arrows_every = max(1, arrows_every)
        self._trail_every = max(1, trail_every)
        self._trail: deque[tuple[float, float, float]] = deque(
            maxlen=max(2, int(trail_s * 500 / self._trail_every)))
        self._last_state: int | None = None
        self._last_sat = 0
        self._health_named: set[str] = set()
        self._rec: rr.RecordingStream | None = None
        self._serving: rr.RecordingStream | None = None
        if mode == "off":
            return
        if params is None:
            from groundstation.configs import load_vehicle

            params = load_vehicle(str(self.metadata.get("vehicle", "fasthex")))
        from controller.model import VehicleModel

        self._model = VehicleModel(params)
        self._spin_limits = (params.rotors.min_spin_hz, params.rotors.max_spin_hz)
        # arrows 0.25 m long at hover thrust
        self._arrow_m_per_n = 0.25 / (params.mass_kg * params.gravity_m_s2 / 6.0)
        self._open(recording_id, grpc_port, web_port, server_memory_limit)
        self._log_static()

    # -- set-up ------------------------------------------------------------------------------
    def _open(self, recording_id: str | None, grpc_port: int, web_port: int,
              memory_limit: str) -> None:
        import rerun as rr

        rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        rec.set_log_time_enabled(False)  # sim_time and tick are the timelines
        sinks: list[Any] = []
        if self.rrd_path is not None:
            sinks.append(rr.FileSink(str(self.rrd_path)))
        if self.mode == "serve":
            sinks.append(rr.GrpcServerSink(bind_ip="127.0.0.1", port=grpc_port,
                                           server_memory_limit=memory_limit))
            self.grpc_url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        elif self.mode == "spawn":
            # the spawned viewer holds the data; its server need not keep a second copy
            rr.spawn(port=grpc_port, connect=False, server_memory_limit="0B")
            self.grpc_url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
            sinks.append(rr.GrpcSink(self.grpc_url))
        rec.set_sinks(*sinks, default_blueprint=blueprint())
        if self.mode == "serve":
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=self.grpc_url)
            self.viewer_url = (f"http://127.0.0.1:{web_port}/?url="
                               + urllib.parse.quote(self.grpc_url or "", safe=""))
        self._rec = rec

    def _log_static(self) -> None:
        import rerun as rr

        rec = self._rec
        assert rec is not None
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for path, names in SCALAR_SERIES.items():
            rec.log(path, rr.SeriesLines(names=list(names), colors=_SERIES_COLORS[path]),
                    static=True)
        m = self._model
        rotors = m.rotor_positions_b_m
        ring = [rotors[i % 6] for i in range(7)]
        arms = [[(0.0, 0.0, 0.0), tuple(p)] for p in rotors]
        rec.log("/world/vehicle", rr.TransformAxes3D(0.3), static=True)
        rec.log("/world/vehicle/arms", rr.LineStrips3D([*arms, ring], colors=[(90, 90, 90)],
                                                       radii=0.008), static=True)
        rec.log("/world/vehicle/rotors", rr.Points3D(rotors, radii=0.03, colors=_ROTOR_RGB,
                                                     labels=[str(i) for i in range(1, 7)]),
                static=True)
        rec.log("/world/reference", rr.TransformAxes3D(0.2), static=True)
        if self.metadata:
            # not static: static data of an entity would hide all of its temporal events
            text = ", ".join(f"{k}: {v}" for k, v in self.metadata.items()
                             if isinstance(v, (str, int, float)))
            self.log_event(0.0, f"flight: {text}", level="INFO")
            self.events_logged -= 1  # counts the caller's events only

    # -- data --------------------------------------------------------------------------------
    def _failed(self, what: str, exc: Exception) -> None:
        """A dashboard fault never reaches the caller (the flight record must go on): the
        dashboard switches itself off with one warning."""
        self.error = f"{what}: {type(exc).__name__}: {exc}"
        _log.warning("rerun dashboard off after an error in %s", self.error)
        rec, self._rec = self._rec, None
        if rec is not None:
            with contextlib.suppress(Exception):
                rec.disconnect()

    def log_rows(self, rows: np.ndarray) -> None:
        """Ship a block of consecutive flight-record rows (structured array)."""
        try:
            self._log_rows(rows)
        except Exception as exc:
            self.rows_logged += len(rows)
            self._failed("log_rows", exc)

    def _log_rows(self, rows: np.ndarray) -> None:
        n = len(rows)
        if self._rec is None or n == 0:
            self.rows_logged += n
            if n:
                self._t_last = float(rows["t_s"][-1])
            return
        import rerun as rr

        rec = self._rec
        s = panel_signals(rows)
        t = s.t_s
        tick = np.arange(self.rows_logged, self.rows_logged + n, dtype=np.int64)
        idx = [rr.TimeColumn("sim_time", duration=t), rr.TimeColumn("tick", sequence=tick)]

        def scalars(path: str, data: npt.ArrayLike) -> None:
            arr = np.asarray(data, dtype=np.float64)
            rec.send_columns(path, indexes=idx,
                             columns=rr.Scalars.columns(scalars=arr.reshape(n, -1)))

        scalars("/position/ref", s.pos_ref_w_m)
        scalars("/position/actual", s.pos_w_m)
        scalars("/position_error", np.column_stack([s.pos_err_mm, s.pos_err_norm_mm]))
        scalars("/attitude/ref", s.eul_ref_deg)
        scalars("/attitude/desired", s.eul_des_deg)
        scalars("/attitude/actual", s.eul_deg)
        scalars("/attitude_error", s.att_err_deg)
        scalars("/spin/actual", s.spin_hz)
        scalars("/lateral_force", np.column_stack([s.r_xy_n, s.lat_force_n]))
        scalars("/tilt", np.column_stack([s.alpha_ref_deg, s.alpha_cmd_deg, s.alpha_deg]))
        scalars("/actuation", s.actuation)
        scalars("/health/saturated_rotors", s.sat_count)
        # the limits only at the block's ends: two points draw the same horizontal line
        ends = np.array([0, n - 1]) if n > 1 else np.array([0])
        lim = np.tile(np.asarray(self._spin_limits, dtype=np.float64), (len(ends), 1))
        rec.send_columns("/spin/limits", indexes=[
            rr.TimeColumn("sim_time", duration=t[ends]),
            rr.TimeColumn("tick", sequence=tick[ends])],
            columns=rr.Scalars.columns(scalars=lim))
        self._log_world(rows, t, tick, s.pos_w_m)
        self._events_from_rows(s.t_s, s.actuation, np.asarray(rows["sat_mask"]))
        self.rows_logged += n
        self._t_last = float(t[-1])

    def _sub(self, tick: npt.NDArray[np.int64], every: int) -> npt.NDArray[np.intp]:
        return np.flatnonzero(tick % every == 0)

    def _log_world(self, rows: np.ndarray, t: npt.NDArray[np.float64],
                   tick: npt.NDArray[np.int64], pos: npt.NDArray[np.float64]) -> None:
        import rerun as rr

        rec = self._rec
        assert rec is not None
        k = self._sub(tick, self._pose_every)
        if len(k):
            idx = [rr.TimeColumn("sim_time", duration=t[k]),
                   rr.TimeColumn("tick", sequence=tick[k])]
            rec.send_columns("/world/vehicle", indexes=idx, columns=rr.Transform3D.columns(
                translation=np.asarray(rows["pos_w_m"][k], np.float32),
                quaternion=_xyzw(rows["q_wb"][k])))
            rec.send_columns("/world/reference", indexes=idx, columns=rr.Transform3D.columns(
                translation=np.asarray(rows["pos_ref_w_m"][k], np.float32),
                quaternion=_xyzw(rows["q_wr"][k])))
        k = self._sub(tick, self._arrows_every)
        if len(k):
            m = self._model
            alpha = np.asarray(rows["alpha_rad"][k], dtype=np.float64)
            thrust = np.asarray(rows["thrust_n"][k], dtype=np.float64)
            vectors = np.concatenate([m.thrust_axes(float(a)) * (f * self._arrow_m_per_n)[:, None]
                                      for a, f in zip(alpha, thrust, strict=True)])
            origins = np.tile(m.rotor_positions_b_m, (len(k), 1))
            cols = rr.Arrows3D.columns(vectors=vectors, origins=origins,
                                       colors=np.tile(np.asarray(_ROTOR_RGB, np.uint8),
                                                      (len(k), 1)))
            rec.send_columns("/world/vehicle/thrust",
                             indexes=[rr.TimeColumn("sim_time", duration=t[k]),
                                      rr.TimeColumn("tick", sequence=tick[k])],
                             columns=cols.partition([6] * len(k)))
        k = self._sub(tick, self._trail_every)
        for j in k:
            self._trail.append((float(pos[j, 0]), float(pos[j, 1]), float(pos[j, 2])))
        if len(k) and len(self._trail) >= 2:
            j = int(k[-1])
            rec.set_time("sim_time", duration=float(t[j]))
            rec.set_time("tick", sequence=int(tick[j]))
            rec.log("/world/trail", rr.LineStrips3D([list(self._trail)], radii=0.005,
                                                    colors=[(255, 0, 255)]))

    def _events_from_rows(self, t: npt.NDArray[np.float64], state: npt.NDArray[np.int64],
                          sat_mask: npt.NDArray[Any]) -> None:
        """Actuation changes and saturation onsets become events."""
        names = {UDT: "UDT (under-actuated)", 1: "fully actuated", MDT: "MDT"}
        prev = self._last_state
        change = np.flatnonzero(np.diff(state)) + 1
        if prev is None or prev != state[0]:
            change = np.concatenate([[0], change])
        for j in change:
            before = names[prev] if prev is not None else "start"
            self.log_event(float(t[j]), f"actuation {before} -> {names[int(state[j])]}")
            prev = int(state[j])
        self._last_state = int(state[-1])
        sat = np.asarray(sat_mask, dtype=np.int64)
        was = np.concatenate([[self._last_sat], sat[:-1]])
        for j in np.flatnonzero((sat != 0) & (was == 0)):
            rotors = [str(i + 1) for i in range(6) if int(sat[j]) >> i & 1]
            self.log_event(float(t[j]), f"saturation: rotor {', '.join(rotors)} clamped",
                           level="WARN")
        self._last_sat = int(sat[-1])

    def log_event(self, t_s: float, text: str, level: str | None = None) -> None:
        """One event (state transition, fault, preflight result) at flight time ``t_s``."""
        self.events_logged += 1
        if self._rec is None:
            return
        import rerun as rr

        t = 0.0 if not math.isfinite(t_s) else float(t_s)
        try:
            self._rec.send_columns(
                "/events", indexes=[rr.TimeColumn("sim_time", duration=[t])],
                columns=rr.TextLog.columns(text=[text], level=[level or _level(text)]))
        except Exception as exc:
            self._failed("log_event", exc)

    def log_event_line(self, line: str) -> None:
        """One line as the flight loop emits it (``"T.TTT s TEXT"``); a line without a time
        stamp is placed at the newest row's time."""
        parsed = parse_events(line)
        if not parsed:
            return
        t, text = parsed[0]
        if not _EVENT_RE.match(line):
            t = self._t_last
        self.log_event(t, text)

    def log_health(self, t_s: float, values: Mapping[str, float]) -> None:
        """Loop/link health values (e.g. ``loop_jitter_p99_ms``, ``link_loss_frac``) at
        ``t_s``; each name becomes the entity ``/health/<name>``."""
        if self._rec is None:
            return
        import rerun as rr

        rec = self._rec
        try:
            for name, v in values.items():
                path = f"/health/{name}"
                if name not in self._health_named:
                    rec.log(path, rr.SeriesLines(names=[name]), static=True)
                    self._health_named.add(name)
                rec.send_columns(path, indexes=[rr.TimeColumn("sim_time", duration=[t_s])],
                                 columns=rr.Scalars.columns(scalars=[float(v)]))
        except Exception as exc:
            self._failed("log_health", exc)

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush everything to the sinks and close the file (the viewer keeps running)."""
        if self._rec is None:
            return
        rec, self._rec = self._rec, None
        try:
            rec.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:  # a viewer that went away: the file sink still closes
            _log.warning("rerun dashboard: %s", exc)
        if self.mode != "serve":
            rec.disconnect()
        else:
            self._serving = rec  # the gRPC server lives as long as its stream

    def __enter__(self) -> Dashboard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def drain_into_dashboard(ring_name: str, capacity: int, dashboard_args: dict[str, Any],
                         events: Any, stop: Any, period_s: float = 0.1) -> None:
    """Body of a telemetry process that feeds only the dashboard: drains the loop's
    :class:`~groundstation.telemetry.TelemetryRing` of record rows and the event queue
    (``"T.TTT s TEXT"`` strings) every ``period_s`` until ``stop`` is set and both are empty.
    ``dashboard_args`` are :class:`Dashboard`'s keyword arguments plus ``mode``."""
    import queue
    import time

    from groundstation.record import RECORD_DTYPE
    from groundstation.telemetry import TelemetryRing

    with contextlib.suppress(OSError):
        os.nice(10)
    ring = TelemetryRing(RECORD_DTYPE, capacity, name=ring_name)
    args = dict(dashboard_args)
    dash = Dashboard(args.pop("mode"), args.pop("rrd_path", None), **args)
    try:
        while True:
            finished = stop.is_set()
            rows = ring.drain()
            dash.log_rows(rows)
            while True:
                try:  # at the end, wait briefly for lines still in the queue's pipe
                    line = events.get(timeout=period_s) if finished else events.get_nowait()
                except queue.Empty:
                    break
                dash.log_event_line(line)
            if finished and not len(rows):
                break
            if not len(rows):
                time.sleep(period_s)
    finally:
        dash.close()
        ring.close()
