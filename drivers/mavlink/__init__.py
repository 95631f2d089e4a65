"""MAVLink bridge: the ground station as a MAVLink2 vehicle for QGroundControl and MAVProxy.

Layers: :mod:`~drivers.mavlink.frames` (world z-up/FLU <-> NED/FRD, pure),
:mod:`~drivers.mavlink.messages` (telemetry snapshot -> pymavlink messages, pure),
:mod:`~drivers.mavlink.signing` (key loading, signature and replay checks),
:mod:`~drivers.mavlink.link` (UDP endpoint by URI, codec), :mod:`~drivers.mavlink.bridge`
(the device: service thread, telemetry rates, commands, parameters, MoCap input).
The wire protocol and command mapping are documented in :mod:`~drivers.mavlink.bridge`.
"""

from drivers.mavlink.bridge import BridgeStats, MavlinkBridge, MavlinkConfig, MavlinkPoseSource
from drivers.mavlink.signing import SigningKeyError, load_signing_key

__all__ = [
    "BridgeStats",
    "MavlinkBridge",
    "MavlinkConfig",
    "MavlinkPoseSource",
    "SigningKeyError",
    "load_signing_key",
]
