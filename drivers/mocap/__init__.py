"""Motion capture: OptiTrack NatNet, VRPN and Qualisys QTM RT clients behind one ``PoseSource``
interface.

Layers: :mod:`~drivers.mocap.natnet`, :mod:`~drivers.mocap.vrpn` and :mod:`~drivers.mocap.qtm`
are pure codecs (bytes <-> frozen dataclasses); :mod:`~drivers.mocap.frames` converts MoCap axes
and units into the ground station's z-up world frame;
:class:`~drivers.mocap.natnet_client.NatNetClient`, :class:`~drivers.mocap.vrpn_client.VrpnClient`
and :class:`~drivers.mocap.qtm_client.QtmClient` own their sockets and receive threads;
:func:`~drivers.mocap.uri.open_pose_source` builds any of them from a URI.
"""
