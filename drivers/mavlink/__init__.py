"""MAVLink bridge: the ground station as a MAVLink2 vehicle for QGroundControl and MAVProxy.

Layers: :mod:`~drivers.mavlink.frames` (world z-up/FLU <-> NED/FRD, pure),
:mod:`~drivers.mavlink.messages` (telemetry snapshot -> pymavlink messages, pure),
:mod:`~drivers.mavlink.signing` (key loading, signature and replay checks),
:mod:`~drivers.mavlink.link` (UDP endpoint by URI, codec), :mod:`~drivers.mavlink.bridge`
(the device: service thread, telemetry rates, commands, parameters, MoCap input).
The wire protocol and command mapping are documented in :mod:`~drivers.mavlink.bridge`.

Wiring in a flight session (outside the 500 Hz loop, in the telemetry process)::

    bridge = MavlinkBridge.from_config(cfg.mavlink, sink, params=operator_params(...))
    bridge.start()                      # wall clock; or bridge.step(t_s) per drained batch
    ...
    bridge.publish(VehicleTelemetry(...))   # newest snapshot, any rate; events ride along
    ...
    bridge.close()

``sink`` is the flight state machine's :class:`~groundstation.operator.OperatorCommandSink`
(``submit(cmd) -> CommandResult``, thread-safe, answers from the current phase with
:func:`~groundstation.operator.decide`, carries the command out asynchronously).
``bridge.mocap`` is a :class:`~drivers.mocap.pose.PoseSource` of MoCap poses received over
MAVLink; ``bridge.gcs_link_ok()`` tells whether a GCS heartbeat is recent.
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
