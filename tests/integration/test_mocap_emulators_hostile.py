"""The emulated MoCap servers survive hostile input on their real sockets: after hundreds of
random and mutated datagrams (and a garbage TCP stream for VRPN) a real client still connects
and reads the pose, and every refused input was counted."""

from __future__ import annotations

import random
import socket

import pytest

from drivers.mocap import natnet, vrpn
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig
from sim_backend.emulators.natnet import NatNetEmulatorConfig, NatNetServer
from sim_backend.emulators.vrpn import VrpnEmulatorConfig, VrpnServer
from sim_backend.vehicle import BenchVehicle

WAIT_S = 10.0
N_DATAGRAMS = 400


def _hostile(rng: random.Random, seeds: list[bytes]) -> bytes:
    if rng.random() < 0.5:
        return rng.randbytes(rng.randrange(0, 300))
    data = bytearray(rng.choice(seeds))
    for _ in range(rng.randrange(1, 5)):
        if data:
            data[rng.randrange(len(data))] = rng.randrange(256)
    return bytes(data)


def test_that_the_natnet_emulator_serves_a_client_after_hostile_datagrams() -> None:
    # Fixture
    rng = random.Random(14)
    seeds = [natnet.encode_connect("ping"), natnet.encode_keepalive(),
             natnet.encode_request_modeldef(), natnet.encode_command("Bitstream,9.9"),
             natnet.encode_command("Bitstream,"), natnet.encode_disconnect()]
    vehicle = BenchVehicle(pos_w_m=(0.5, -1.0, 2.0))
    with NatNetServer(vehicle, NatNetEmulatorConfig(command_port=0, rate_hz=200.0)) as server:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
            attacker.bind(("127.0.0.1", 0))
            # Test
            for _ in range(N_DATAGRAMS):
                attacker.sendto(_hostile(rng, seeds), ("127.0.0.1", server.command_port))
            with NatNetClient(NatNetConfig(command_port=server.command_port)) as client:
                assert client.wait_frames(20, WAIT_S)
                s = client.latest()
        # Assert
        assert s is not None and s.valid
        assert s.pos_w_m == pytest.approx((0.5, -1.0, 2.0), abs=1e-6)  # float32 on the wire
        assert server.counters.malformed_requests > 0
        assert server.counters.input_errors == 0


def test_that_the_vrpn_emulator_serves_a_client_after_hostile_requests_and_streams() -> None:
    # Fixture
    rng = random.Random(15)
    lob_seeds = [vrpn.encode_lob("127.0.0.1", 1), vrpn.encode_lob("10.1.2.3", 3883)]
    stream_seeds = [vrpn.encode_cookie() + vrpn.encode_message(0, -5, b"", 1.0)]
    with VrpnServer(BenchVehicle(), VrpnEmulatorConfig(port=0, rate_hz=200.0)) as server:
        # Test: connection requests that do not parse, name a third host or a closed port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
            for _ in range(N_DATAGRAMS):
                attacker.sendto(_hostile(rng, lob_seeds), ("127.0.0.1", server.port))
        # ... and TCP clients that send garbage instead of a cookie: each is dropped
        for _ in range(20):
            with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as bad:
                bad.sendall(b"X" + _hostile(rng, stream_seeds) + bytes(24))
                while bad.recv(4096):  # the server's cookie, then the end of the stream
                    pass
        with VrpnClient(VrpnConfig(port=server.port)) as client:
            assert client.wait_frames(20, WAIT_S)
            s = client.latest()
        # Assert
        assert s is not None and s.valid
        assert server.dropped_inputs >= 20  # every garbage stream, plus refused requests
