"""MoCap device URIs -> configs and (unstarted) PoseSource devices.

Forms (options are query parameters; defaults in brackets):

``natnet://SERVER[:COMMAND_PORT]?local=IP&mode=unicast|multicast&data_port=N&group=IP&body=NAME&version=X.Y&require_version=0|1&up=y|z&units=m|mm&delay_ms=F&range_m=F``
    OptiTrack Motive. ``SERVER`` is the Motive PC, ``COMMAND_PORT`` [1510]; ``local`` is this
    PC's address on the MoCap network [127.0.0.1]; ``mode`` [unicast]; ``data_port`` [1511] and
    ``group`` [239.255.42.99] for multicast; ``body`` the rigid-body name [the first defined];
    ``version`` a bitstream to request (unicast only) [the server's]; a request the server
    does not confirm in its SERVERINFO is a warning, or an error with ``require_version=1``
    [0]; ``up`` the streaming up
    axis [y]; ``units`` [m]; ``delay_ms`` the network delay added to the reported latency [0];
    ``range_m`` the workspace radius beyond which a pose is dropped as implausible [100].
    Example: ``natnet://127.0.0.1?local=127.0.0.1&mode=unicast&body=fasthex``.

``vrpn://TRACKER@HOST[:PORT]?sensor=N&up=y|z&units=m|mm&latency_ms=F&stale_ms=F&range_m=F&handshake=auto|classic|tcp``
    A VRPN tracker (Vicon Tracker, Motive, QTM). ``PORT`` [3883]; ``sensor`` [0]; ``up`` [z];
    ``units`` [m]; ``latency_ms`` the system latency to subtract [0]; ``stale_ms`` after which
    a silent tracker is reported missing [50]; ``range_m`` as for NatNet [100]; ``handshake``
    [auto: the classic UDP request and call-back, then direct TCP after 1 s]. Example:
    ``vrpn://Tracker0@127.0.0.1:3883``.

``motioncapture://SYSTEM?host=HOST&body=NAME&up=y|z&units=m|mm&latency_ms=F&stale_ms=F&range_m=F``
    Any system libmotioncapture reads (optional extra ``fasthex[motioncapture]``): ``vicon``
    (Vicon DataStream; ``host`` may be ``HOST:PORT`` [801]), ``optitrack``, ``qualisys``
    (``HOST:PORT`` names QTM's little-endian RT port [22223] as ``qtm://`` does; the library
    takes the base port below it, so the adapter passes ``PORT - 1``; frames come over UDP to
    the fixed local port 6734), ``vrpn`` (``host`` as ``HOST:PORT`` [3883]). ``up`` [z; y for
    optitrack]; the other options as for VRPN. The library runs in a child process, so a
    silent host costs ``connect_timeout_s`` and a clear error, never a frozen ground station
    (see :mod:`drivers.mocap.motioncapture_client`). Example:
    ``motioncapture://vicon?host=192.168.1.5&body=fasthex``.

``qtm://HOST[:PORT]?body=NAME&component=6d|6dres|6deuler|6deulerres&frequency_hz=F&udp=0|1&local=IP&up=y|z&units=m|mm&latency_ms=F&range_m=F``
    Qualisys QTM RT. ``PORT`` [22223, the little-endian RT port]; ``body`` the 6DOF body name
    [the first defined]; ``component`` [6d]; ``frequency_hz`` the stream rate [0: every
    frame]; ``udp=1`` streams frames over UDP to a port of this PC bound on ``local``
    [0.0.0.0] instead of the TCP connection [0]; ``up`` [z]; ``units`` [mm]; ``latency_ms``
    the system latency to subtract [0]; ``range_m`` as for NatNet [100]. Example:
    ``qtm://192.168.1.10?body=fasthex``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from urllib.parse import parse_qs, urlsplit

from config.schema import ConfigValueError
from drivers.mocap.frames import FrameConfig
from drivers.mocap.motioncapture_client import (
    SYSTEM_UP_AXIS,
    MotionCaptureClient,
    MotionCaptureConfig,
)
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import PoseLimits
from drivers.mocap.qtm_client import QtmClient, QtmConfig
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig

NATNET_FORM = ("natnet://SERVER[:PORT]?local=IP&mode=unicast|multicast&data_port=N&group=IP"
               "&body=NAME&version=X.Y&require_version=0|1&up=y|z&units=m|mm&delay_ms=F"
               "&range_m=F")
VRPN_FORM = ("vrpn://TRACKER@HOST[:PORT]?sensor=N&up=y|z&units=m|mm&latency_ms=F&stale_ms=F"
             "&range_m=F&handshake=auto|classic|tcp")
MOTIONCAPTURE_FORM = ("motioncapture://vicon|optitrack|qualisys|vrpn?host=HOST&body=NAME"
                      "&up=y|z&units=m|mm&latency_ms=F&stale_ms=F&range_m=F")
QTM_FORM = ("qtm://HOST[:PORT]?body=NAME&component=6d|6dres|6deuler|6deulerres&frequency_hz=F"
            "&udp=0|1&local=IP&up=y|z&units=m|mm&latency_ms=F&range_m=F")


class MocapUriError(ValueError):
    """A MoCap URI that does not parse; the message shows the expected form."""


def _options(query: str, allowed: set[str], uri: str, form: str) -> dict[str, str]:
    opts = {k: v[-1] for k, v in parse_qs(query, keep_blank_values=True).items()}
    unknown = set(opts) - allowed
    if unknown:
        raise MocapUriError(f"{uri}: unknown option(s) {sorted(unknown)}; expected {form}")
    return opts


def _frames(opts: dict[str, str], default_up: str, default_units: str = "m") -> FrameConfig:
    return FrameConfig(up_axis=opts.get("up", default_up),  # type: ignore[arg-type]
                       units=opts.get("units", default_units))  # type: ignore[arg-type]


def _flag(opts: dict[str, str], key: str) -> bool:
    value = opts.get(key, "0")
    if value not in ("0", "1"):
        raise ValueError(f"{key} must be 0 or 1, not {value!r}")
    return value == "1"


def _limits(opts: dict[str, str]) -> PoseLimits:
    if "range_m" not in opts:
        return PoseLimits()
    return PoseLimits(max_range_m=float(opts["range_m"]))


def parse_uri(uri: str) -> NatNetConfig | VrpnConfig | MotionCaptureConfig | QtmConfig:
    """Parse a ``natnet://``, ``vrpn://``, ``motioncapture://`` or ``qtm://`` URI. Raises
    :class:`MocapUriError`."""
    parts = urlsplit(uri)
    try:
        if parts.scheme == "natnet":
            opts = _options(parts.query, {"local", "mode", "data_port", "group", "body",
                                          "version", "require_version", "up", "units",
                                          "delay_ms", "range_m"}, uri, NATNET_FORM)
            if not parts.hostname:
                raise MocapUriError(f"{uri}: no server address; expected {NATNET_FORM}")
            d = NatNetConfig()
            return NatNetConfig(
                server_ip=parts.hostname, local_ip=opts.get("local", d.local_ip),
                mode=opts.get("mode", d.mode),  # type: ignore[arg-type]
                command_port=parts.port or d.command_port,
                data_port=int(opts.get("data_port", d.data_port)),
                multicast_group=opts.get("group", d.multicast_group),
                body=opts.get("body", ""), version=opts.get("version", ""),
                require_version=_flag(opts, "require_version"),
                network_delay_s=float(opts.get("delay_ms", 0.0)) / 1000.0,
                frames=_frames(opts, "y"), limits=_limits(opts))
        if parts.scheme == "vrpn":
            opts = _options(parts.query, {"sensor", "up", "units", "latency_ms", "stale_ms",
                                          "range_m", "handshake"}, uri, VRPN_FORM)
            if not parts.username or not parts.hostname:
                raise MocapUriError(f"{uri}: needs TRACKER@HOST; expected {VRPN_FORM}")
            d2 = VrpnConfig()
            return VrpnConfig(
                tracker=parts.username, host=parts.hostname, port=parts.port or d2.port,
                sensor=int(opts.get("sensor", 0)),
                latency_s=float(opts.get("latency_ms", 0.0)) / 1000.0,
                stale_after_s=float(opts.get("stale_ms", d2.stale_after_s * 1000)) / 1000.0,
                frames=_frames(opts, "z"), limits=_limits(opts),
                handshake=opts.get("handshake", d2.handshake))  # type: ignore[arg-type]
        if parts.scheme == "motioncapture":
            opts = _options(parts.query, {"host", "body", "up", "units", "latency_ms",
                                          "stale_ms", "range_m"}, uri, MOTIONCAPTURE_FORM)
            system = parts.hostname or ""
            d3 = MotionCaptureConfig
            return MotionCaptureConfig(
                system=system, host=opts.get("host", ""), body=opts.get("body", ""),
                latency_s=float(opts.get("latency_ms", 0.0)) / 1000.0,
                stale_after_s=float(opts.get("stale_ms", d3.stale_after_s * 1000)) / 1000.0,
                frames=_frames(opts, SYSTEM_UP_AXIS.get(system, "z")), limits=_limits(opts))
        if parts.scheme == "qtm":
            opts = _options(parts.query, {"body", "component", "frequency_hz", "udp", "local",
                                          "up", "units", "latency_ms", "range_m"}, uri, QTM_FORM)
            if not parts.hostname:
                raise MocapUriError(f"{uri}: no QTM host; expected {QTM_FORM}")
            if opts.get("udp", "0") not in ("0", "1"):
                raise MocapUriError(f"{uri}: udp must be 0 or 1; expected {QTM_FORM}")
            dq = QtmConfig()
            return QtmConfig(
                host=parts.hostname, port=parts.port or dq.port, body=opts.get("body", ""),
                component=opts.get("component", dq.component),
                frequency_hz=float(opts.get("frequency_hz", 0.0)),
                udp=opts.get("udp", "0") == "1", local_ip=opts.get("local", dq.local_ip),
                latency_s=float(opts.get("latency_ms", 0.0)) / 1000.0,
                frames=_frames(opts, "z", "mm"), limits=_limits(opts))
    except (ConfigValueError, ValueError) as exc:
        if isinstance(exc, MocapUriError):
            raise
        raise MocapUriError(f"{uri}: {exc}") from exc
    raise MocapUriError(f"{uri}: unknown scheme {parts.scheme!r}; expected {NATNET_FORM}, "
                        f"{VRPN_FORM}, {MOTIONCAPTURE_FORM} or {QTM_FORM}")


def open_pose_source(uri: str, clock: Callable[[], int] | None = None, **overrides: object
                     ) -> NatNetClient | VrpnClient | MotionCaptureClient | QtmClient:
    """An unstarted device for ``uri`` (call ``start()`` or use it as a context manager).

    ``overrides`` replace config fields (e.g. ``body="fasthex"`` or ``frames=...``).
    """
    cfg = parse_uri(uri)
    if overrides:
        try:
            cfg = dataclasses.replace(cfg, **overrides)  # type: ignore[arg-type]
        except (TypeError, ConfigValueError) as exc:
            raise MocapUriError(f"{uri}: {exc}") from exc
    kwargs = {} if clock is None else {"clock": clock}
    if isinstance(cfg, NatNetConfig):
        return NatNetClient(cfg, **kwargs)
    if isinstance(cfg, MotionCaptureConfig):
        return MotionCaptureClient(cfg) if clock is None else MotionCaptureClient(cfg, clock)
    if isinstance(cfg, QtmConfig):
        return QtmClient(cfg, **kwargs)
    return VrpnClient(cfg, **kwargs)
