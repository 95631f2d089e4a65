"""MAVLink link layer: the ground station's wire to a GCS (QGroundControl, MAVProxy).

Only what knows MAVLink and nothing of flights lives here:
:mod:`~drivers.mavlink.frames` (world z-up/FLU <-> NED/FRD, pure),
:mod:`~drivers.mavlink.signing` (key loading, signature, replay and staleness checks),
:mod:`~drivers.mavlink.link` (UDP endpoint by URI, codec),
:mod:`~drivers.mavlink.config` (the link's settings) and
:mod:`~drivers.mavlink.mocap` (MoCap poses received over MAVLink, range-checked).

The bridge that maps flight phases, telemetry snapshots and operator commands onto MAVLink is
a ground-station part: :mod:`groundstation.mavlink_bridge` (and its session wiring,
:mod:`groundstation.gcs`).
"""

from drivers.mavlink.config import MavlinkConfig
from drivers.mavlink.mocap import MavlinkPoseSource
from drivers.mavlink.signing import SigningKeyError, load_signing_key

__all__ = [
    "MavlinkConfig",
    "MavlinkPoseSource",
    "SigningKeyError",
    "load_signing_key",
]
