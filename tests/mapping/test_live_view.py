"""The Foxglove live view: a real WebSocket client (the Foxglove protocol, `foxglove.sdk.v1`, spoken over
a plain socket) connects to the server, sees the map's channels advertised, subscribes and receives what a
finished window publishes; the config switch is validated."""

import base64
import hashlib
import json
import os
import socket
import struct
import threading

import numpy as np
import pytest

from daemon.spine.config import ConfigError, parse_config
from daemon.spine.mapper_config import LiveViewConfig
from tests.daemon_fixtures import REPO

pytest.importorskip("foxglove")  # the `live-view` extra (also in `test`)

from mapping.live.live_view import publish_window, start_live_view, stop_live_view  # noqa: E402

WS_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
TOPICS = {"/map/bev_rgb", "/map/bev_semantics", "/map/bev_elevation", "/map/elevation", "/map/trajectory"}


class FoxgloveClient:
    """The client side of RFC 6455 with the Foxglove subprotocol: text frames are JSON, binary frames data."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n").encode())
        self.stream = self.sock.makefile("rb")
        head = b""
        while not head.endswith(b"\r\n\r\n"):
            head += self.stream.read(1)
        lines = head.decode().split("\r\n")
        assert " 101 " in lines[0], lines[0]
        headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
        accept = base64.b64encode(hashlib.sha1((key + WS_GUID).encode()).digest()).decode()
        assert headers["sec-websocket-accept"] == accept
        assert headers["sec-websocket-protocol"] == "foxglove.sdk.v1"

    def receive(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next complete message (fragments joined, pings skipped)."""
        payload, opcode = b"", None
        while True:
            b0, b1 = self.stream.read(2)
            n = b1 & 0x7F
            if n == 126:
                (n,) = struct.unpack(">H", self.stream.read(2))
            elif n == 127:
                (n,) = struct.unpack(">Q", self.stream.read(8))
            data = self.stream.read(n)
            if b0 & 0x0F in (0x9, 0xA):  # ping / pong
                continue
            opcode = opcode if b0 & 0x0F == 0 else b0 & 0x0F
            payload += data
            if b0 & 0x80:
                return opcode, payload

    def send_json(self, obj: dict) -> None:
        data = json.dumps(obj).encode()
        mask = os.urandom(4)
        head = bytes([0x81]) + (bytes([0x80 | len(data)]) if len(data) < 126
                                else bytes([0x80 | 126]) + struct.pack(">H", len(data)))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def close(self) -> None:
        self.stream.close()
        self.sock.close()


def test_live_view_switch_is_off_by_default_and_validated(tmp_path):
    import yaml

    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    assert parse_config(data).mapper.live_view == LiveViewConfig(enabled=False, bind_address="127.0.0.1", port=8765)
    data["mapper"]["live_view"] = {"enabled": True, "port": 0}
    assert parse_config(data).mapper.live_view.enabled
    for bad in ({"port": 70000}, {"enabled": True, "colour": "red"}):
        data["mapper"]["live_view"] = bad
        with pytest.raises(ConfigError, match="mapper.live_view"):
            parse_config(data)


def test_a_client_sees_the_map_channels_and_receives_a_finished_window():
    view = start_live_view(LiveViewConfig(enabled=True, port=0))
    client = FoxgloveClient(view.port)
    try:
        channels = {}
        while not TOPICS <= set(channels):
            opcode, payload = client.receive()
            assert opcode == 1  # before any subscription only JSON: serverInfo, advertise
            message = json.loads(payload)
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        assert channels["/map/bev_rgb"]["schemaName"] == "foxglove.CompressedImage"
        assert channels["/map/elevation"]["schemaName"] == "foxglove.Grid"
        client.send_json({"op": "subscribe", "subscriptions": [
            {"id": 1, "channelId": channels["/map/bev_rgb"]["id"]},
            {"id": 2, "channelId": channels["/map/elevation"]["id"]}]})
        elevation = np.full((20, 30), np.nan, np.float32)
        elevation[5:15, 3:27] = np.linspace(-0.1, 0.1, 24, dtype=np.float32)
        rgb = np.zeros((20, 30, 3), np.uint8)
        rgb[5:15, 3:27] = (200, 120, 40)
        images = {"rgb": rgb, "semantics": rgb, "elevation": rgb}
        stamp = 1_234_567_890_123
        got: dict[int, bytes] = {}
        done = threading.Event()

        def publish_until_received() -> None:  # a subscription takes effect asynchronously
            while not done.wait(0.1):
                publish_window(view, stamp, images, elevation, (10.0, -5.0), 0.1, np.array([[10.0, 0, 0], [12, 0, 0]]))

        publisher = threading.Thread(target=publish_until_received)
        publisher.start()
        try:
            while len(got) < 2:
                opcode, payload = client.receive()
                if opcode == 2 and payload[0] == 1:  # messageData: subscription id, log time, message
                    sub, log_time = struct.unpack_from("<IQ", payload, 1)
                    assert log_time == stamp
                    got[sub] = payload[13:]
        finally:
            done.set()
            publisher.join()
        assert view.published >= 1
        assert set(got) == {1, 2}, got.keys()
        assert b"\x89PNG" in got[1] and b"png" in got[1]
        assert elevation[7].tobytes() in got[2] and b"elevation" in got[2]
    finally:
        client.close()
        stop_live_view(view)
