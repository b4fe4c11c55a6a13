"""Fixtures for the live-link tests: a small real scene, a raw test viewer."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

LAB_BLEND = ROOT / "blend_scenes" / "aces_lab" / "aces_lab.blend"
LAB_SCENE = ROOT / "blend_scenes" / "aces_lab" / "scene"


@pytest.fixture(scope="session")
def wire():
    """The live link's wire format (:mod:`isac_twin.contract.wire`)."""
    from isac_twin.contract import wire as w

    return w


@pytest.fixture(scope="session")
def box_scene_dir(tmp_path_factory):
    """A 6 x 4 x 3 m concrete box room with AP1 -> robot1 (isac_twin.scene.synthetic)."""
    from isac_twin.scene.synthetic import box_room

    return box_room(tmp_path_factory.mktemp("box"))


@pytest.fixture(scope="session")
def box_twin_factory(box_scene_dir):
    """Builds fresh :class:`isac_twin.twin.twin.Twin` s on the box room (real Sionna tracing, PHY)."""
    from isac_twin import Twin

    def make(**kw):
        return Twin.from_scene(box_scene_dir, **kw)

    return make


class RawViewer:
    """A blocking test viewer: raw socket + the wire decoder, every call with a timeout."""

    def __init__(self, address, wire, *, rcvbuf: int | None = None, timeout: float = 10.0):
        self.wire = wire
        self.sock = socket.socket()
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(timeout)
        self.sock.connect(address)
        self.dec = wire.Decoder("e2v", peer="test-engine")
        self.got: list[dict] = []

    def send(self, msg: dict) -> None:
        self.sock.sendall(self.wire.encode(msg, check=False))

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def hello(self, **kw) -> None:
        self.send(self.wire.hello("viewer", "test", **kw))

    def until(self, pred, timeout: float = 20.0) -> dict:
        """Read until a message satisfies ``pred``; return it (fails on timeout or EOF)."""
        end = time.monotonic() + timeout
        for m in self.got:
            if pred(m):
                self.got.remove(m)
                return m
        while time.monotonic() < end:
            self.sock.settimeout(max(0.01, end - time.monotonic()))
            try:
                data = self.sock.recv(1 << 20)
            except socket.timeout:
                break
            if not data:
                raise ConnectionError("the server closed the connection")
            self.got.extend(self.dec.feed(data))
            for m in self.got:
                if pred(m):
                    self.got.remove(m)
                    return m
        raise TimeoutError("no matching message within the timeout")

    def closed_by_peer(self, timeout: float = 5.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.sock.settimeout(max(0.01, end - time.monotonic()))
            try:
                data = self.sock.recv(1 << 20)
            except socket.timeout:
                return False
            except ConnectionResetError:
                return True
            if not data:
                return True
            self.got.extend(self.dec.feed(data))
        return False

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def raw_viewer(wire):
    made = []

    def connect(address, **kw):
        v = RawViewer(address, wire, **kw)
        made.append(v)
        return v

    yield connect
    for v in made:
        v.close()


