"""``fasthex mocap list|watch URI``: what a lab checks before every flight.

- ``list``: the rigid bodies the server defines (NatNet: name, id, marker count; QTM: index
  and name of each 6DOF body) or the trackers it announces (VRPN), with the server's name,
  version and stream rate.
- ``watch [--body NAME] [--interval S] [--frames N]``: one live terminal line with the
  world-frame pose (m, deg), the measured rate, the latency, the age and the dropped/invalid
  counts, refreshed every ``--interval`` seconds (on a fixed grid: a late line does not shift
  the next ones); ``--frames N`` prints a last line once N frames arrived. Ctrl-C ends it.

URIs (see :mod:`drivers.mocap.uri`)::

    natnet://127.0.0.1?local=127.0.0.1&mode=unicast           Motive, unicast on this PC
    natnet://192.168.1.10?local=192.168.1.20&mode=multicast   Motive on the lab network
    vrpn://Tracker0@127.0.0.1:3883                             VRPN tracker (Vicon, QTM)
    motioncapture://vicon?host=192.168.1.5&body=fasthex      Vicon through libmotioncapture
    qtm://192.168.1.10?body=fasthex                            Qualisys QTM RT (TCP 22223)

Try it against the emulated vehicle: ``fasthex emulate`` prints the MoCap URI to use.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.mocap.motioncapture_client import MotionCaptureClient
    from drivers.mocap.natnet_client import NatNetClient
    from drivers.mocap.pose import FrameWaits, MocapStats, PoseSample
    from drivers.mocap.qtm_client import QtmClient
    from drivers.mocap.vrpn_client import VrpnClient

NAME = "mocap"
HELP = "list MoCap rigid bodies or watch one live (NatNet, VRPN, QTM or motioncapture URI)"


URI_HELP = """MoCap URIs:
  natnet://SERVER[:PORT]?local=IP&mode=unicast|multicast&data_port=N&group=IP&body=NAME
           &version=X.Y&require_version=0|1&up=y|z&units=m|mm&delay_ms=F
      OptiTrack Motive; PORT = command port (1510); local = this PC's address on the MoCap
      network; unicast (default) or multicast (group 239.255.42.99, data port 1511);
      version = bitstream to request (unicast only; the server's SERVERINFO must confirm
      it, else its own version is read with a warning, or require_version=1 fails);
      up = streaming up axis (default y).
  vrpn://TRACKER@HOST[:PORT]?sensor=N&up=y|z&units=m|mm&latency_ms=F&stale_ms=F
           &handshake=auto|classic|tcp
      a VRPN tracker (Vicon Tracker, Motive, QTM), port 3883, up axis z by default;
      handshake: the classic UDP request and call-back, then direct TCP after 1 s (auto).
  motioncapture://vicon|optitrack|qualisys|vrpn?host=HOST&body=NAME&up=y|z&units=m|mm
      any system libmotioncapture reads (pip install "fasthex[motioncapture]"); Vicon's
      DataStream this way; host may be HOST:PORT (qualisys: the RT port, 22223); up axis z
      (y for optitrack).
  qtm://HOST[:PORT]?body=NAME&component=6d|6dres|6deuler|6deulerres&frequency_hz=F&udp=0|1
           &local=IP&up=y|z&units=m|mm&latency_ms=F
      Qualisys QTM RT; PORT = little-endian RT port (22223); body = 6DOF body name (default:
      the first); frequency_hz = stream rate (default every frame); udp=1 streams frames over
      UDP; Z-up millimetres by default.
examples:
  fasthex mocap list  "natnet://127.0.0.1?local=127.0.0.1&mode=unicast"
  fasthex mocap watch "natnet://192.168.1.10?local=192.168.1.20&mode=multicast" --body fasthex
  fasthex mocap watch vrpn://Tracker0@127.0.0.1:3883
  fasthex mocap watch "qtm://192.168.1.10?body=fasthex"
"""


URI_ARG_HELP = "natnet://SERVER?..., vrpn://TRACKER@HOST or qtm://HOST?..."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = URI_HELP
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    sub = parser.add_subparsers(dest="mocap_action", metavar="ACTION", required=True)
    p_list = sub.add_parser("list", help="list the rigid bodies / trackers of a MoCap server",
                            epilog=URI_HELP,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    p_list.add_argument("uri", metavar="URI", help=URI_ARG_HELP)
    p_watch = sub.add_parser("watch", help="show the live pose, rate and latency of one body",
                             epilog=URI_HELP,
                             formatter_class=argparse.RawDescriptionHelpFormatter)
    p_watch.add_argument("uri", metavar="URI", help=URI_ARG_HELP)
    p_watch.add_argument("--body", default="", help="rigid-body name (NatNet, QTM); default: "
                         "the URI's body option, else the first defined")
    p_watch.add_argument("--frames", type=int, default=0,
                         help="stop after this many frames (0: until Ctrl-C)")
    p_watch.add_argument("--interval", type=float, default=0.2,
                         help="seconds between status lines (default 0.2)")


def _open(uri: str, body: str = ""
          ) -> NatNetClient | VrpnClient | MotionCaptureClient | QtmClient:
    from drivers.mocap.pose import MocapError
    from drivers.mocap.uri import MocapUriError, open_pose_source
    from groundstation.cli import UserError

    try:
        dev = open_pose_source(uri, body=body) \
            if body and uri.startswith(("natnet:", "motioncapture:", "qtm:")) \
            else open_pose_source(uri)
        dev.start()
    except (MocapUriError, MocapError) as exc:
        raise UserError(str(exc)) from exc
    return dev


def _list(uri: str) -> int:
    from drivers.mocap.natnet_client import NatNetClient
    from drivers.mocap.qtm_client import QtmClient
    from drivers.mocap.vrpn_client import VrpnClient

    dev = _open(uri)
    try:
        if isinstance(dev, NatNetClient):
            info = dev.server_info
            assert info is not None and dev.models is not None
            dev.wait_for_rate(2.0)
            st = dev.stats()
            print(f"{info.app_name} {'.'.join(map(str, info.app_version))}, NatNet "
                  f"{'.'.join(map(str, dev.version or ()))}, "
                  f"{'multicast' if info.is_multicast else 'unicast'}, {st.rate_hz:.0f} Hz")
            for rb in dev.models.rigid_bodies:
                print(f"  {rb.body_id:4d}  {rb.name:24s} {len(rb.marker_positions)} markers")
            if not dev.models.rigid_bodies:
                print("  (no rigid bodies defined)")
        elif isinstance(dev, QtmClient):
            dev.wait_frames(50, 2.0)
            st = dev.stats()
            print(f"QTM RT {dev.config.name}, {dev.config.component}, {st.rate_hz:.0f} Hz")
            for index, name in enumerate(dev.bodies()):
                print(f"  {index:4d}  {name}")
        else:
            dev.wait_for_rate(2.0)
            st = dev.stats()
            names = dev.trackers() if isinstance(dev, VrpnClient) else list(dev.bodies())
            for name in names:
                print(f"  {name}  ({st.rate_hz:.0f} Hz on the configured "
                      f"{'sensor' if isinstance(dev, VrpnClient) else 'body'})")
    finally:
        dev.close()
    return 0


def format_status(sample: PoseSample | None, stats: MocapStats) -> str:
    """One status line (also used by tests). Before the first frame there is no rate, latency
    or age to show: only what went wrong meanwhile; unknown values print as ``--``."""
    counts = f"drop {stats.frames_dropped} inv {stats.invalid_samples} " \
        f"bad {stats.malformed_packets}"
    if sample is None:
        wrong = stats.frames_dropped or stats.invalid_samples or stats.malformed_packets
        return "waiting for frames..." + (f"  {counts}" if wrong else "")
    age_s = stats.age_s if math.isinf(stats.age_s) else min(stats.age_s, 99.0)
    head = f"{stats.rate_hz:6.1f} Hz  lat {_ms(stats.latency_s, 5)} ms  " \
        f"age {_ms(age_s, 6)} ms  {counts}"
    if not sample.valid:
        return f"#{sample.frame_number} {sample.body_name}: {sample.status.value.upper()}  " \
            f"{head}"
    w, x, y, z = sample.q_wb
    roll = math.degrees(math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x)))))
    yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    p = sample.pos_w_m
    return (f"#{sample.frame_number} {sample.body_name}: p [{p[0]:+7.3f} {p[1]:+7.3f} "
            f"{p[2]:+7.3f}] m  rpy [{roll:+6.1f} {pitch:+6.1f} {yaw:+7.1f}] deg  {head}")


def _ms(value_s: float, width: int) -> str:
    """A duration in ms; ``--`` when unknown (NaN: no latency known, inf: no valid sample)."""
    return f"{value_s * 1e3:{width}.1f}" if math.isfinite(value_s) else "--".rjust(width)


class WatchPacer:
    """The clock ``watch`` prints by and how it waits between lines (wall time; a test swaps in
    one that steps an emulator in lockstep)."""

    def now_s(self) -> float:
        return time.monotonic()

    def wait(self, dev: FrameWaits, until_frames: int, timeout_s: float) -> None:
        """Wait ``timeout_s``, or less once ``until_frames`` frames arrived (0: no target)."""
        if until_frames:
            dev.wait_for_total(until_frames, timeout_s)
        else:
            time.sleep(timeout_s)


PACER = WatchPacer()


def _watch(args: argparse.Namespace) -> int:
    if not args.interval > 0.0:
        from groundstation.cli import UserError
        raise UserError(f"--interval must be > 0 s, got {args.interval:g}")
    dev = _open(args.uri, args.body)
    tty = sys.stdout.isatty()
    pacer = PACER
    try:
        next_line_s = pacer.now_s()
        while True:
            done = bool(args.frames) and dev.frames_seen >= args.frames
            now_s = pacer.now_s()
            if done or now_s >= next_line_s:
                line = format_status(dev.latest(), dev.stats())
                if tty:
                    sys.stdout.write("\r\x1b[K" + line)
                else:
                    sys.stdout.write(line + "\n")
                sys.stdout.flush()
                # the next slot of the grid after now: a late line does not shift the others
                next_line_s += args.interval * (math.floor((now_s - next_line_s)
                                                           / args.interval) + 1)
            if done:
                break
            pacer.wait(dev, args.frames, next_line_s - now_s)
    except KeyboardInterrupt:
        pass
    finally:
        if tty:
            sys.stdout.write("\n")
        dev.close()
    return 0


def run(args: argparse.Namespace) -> int:
    if args.mocap_action == "list":
        return _list(args.uri)
    return _watch(args)
