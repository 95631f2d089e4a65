"""Motion capture: OptiTrack NatNet and VRPN clients behind one ``PoseSource`` interface.

Layers: :mod:`~drivers.mocap.natnet` and :mod:`~drivers.mocap.vrpn` are pure codecs (bytes <->
frozen dataclasses); :mod:`~drivers.mocap.frames` converts MoCap axes and units into the
ground station's z-up world frame; :class:`~drivers.mocap.natnet_client.NatNetClient` and
:class:`~drivers.mocap.vrpn_client.VrpnClient` own their sockets and receive threads;
:func:`~drivers.mocap.uri.open_pose_source` builds either from a URI.
"""
