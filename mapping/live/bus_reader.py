"""The live worker's bus thread: every topic the mapper needs, read losslessly into the disk spool (the small
streams, GNSS/IMU/wheels/anchors, also into memory; of the Lidar's packets or point clouds every n-th scan), and the
log segments the recorder or player name."""

from __future__ import annotations

import json
import threading
import time

from daemon.bus import pubsub
from daemon.spine.config import CarConfig
from daemon.spine.health import HealthCounters
from daemon.spine.topics import (
    GNSS_FIX,
    IMU,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    camera_topic,
    health_topic,
    mask_topic,
    topic_table,
)
from drivers.lidar.ouster_metadata import OusterMetadata
from mapping.inputs.lidar_ground import VendorDecoding, keeps_scan, scan_number
from mapping.live.keyframe_spool import KeyframeSpool

STALLED_TOPIC_NS = 30_000_000_000  # a topic this far behind the newest message is not waited for
DRAIN_QUIET_S = 1.0  # at shutdown: the bus counts as drained after this long without a message
SMALL_TOPICS = (GNSS_FIX, IMU, WHEEL_SPEEDS, TIME_ANCHOR)
SEGMENT_SOURCES = (health_topic("recorder"), health_topic("replay"))


class BusReader(threading.Thread):
    """Reads every topic the mapper needs into the spool (and the small streams into memory)."""

    def __init__(self, config: CarConfig, spool: KeyframeSpool, lock: threading.Lock, health: HealthCounters,
                 last_seq: dict[str, int], lidar_decoding: OusterMetadata | VendorDecoding | None):
        super().__init__(name="mapper-bus", daemon=True)
        self.config = config
        self.spool = spool
        self.lock = lock
        self.health = health
        self.last_seq = last_seq
        self.small: dict[str, list] = {t: [] for t in SMALL_TOPICS}
        self.segments: dict[str, list[int]] = {}  # segment name -> [first, last] host ns seen open
        self.stop_requested = threading.Event()
        self.drained = threading.Event()
        cams = [c.name for c in config.sensors.cameras]
        table = topic_table(config)
        self.topics = [t for t in [camera_topic(c) for c in cams] + [mask_topic(c) for c in cams]
                       + [LIDAR_PACKETS, LIDAR_POINTS, GNSS_FIX, IMU, WHEEL_SPEEDS, TIME_ANCHOR] if t in table]
        self.subs: dict[str, pubsub.Subscriber] = {}
        self.side: dict[str, pubsub.Subscriber] = {}
        self.lidar_count = 0
        self.lidar_decoding = lidar_decoding  # which scan a Lidar message belongs to (scan_number)
        self.last_message_ns = time.monotonic_ns()
        self.lost = 0
        self.newest: dict[str, int] = {}  # topic -> newest host time received

    def attach(self) -> None:
        """Subscribe to every topic whose ring exists (again later for the others)."""
        for topic in self.topics:
            if topic not in self.subs:
                try:
                    self.subs[topic] = pubsub.open_subscriber(self.config, topic, start="oldest", lossless=True)
                except FileNotFoundError:
                    pass
        for topic in SEGMENT_SOURCES:
            if topic not in self.side:
                try:
                    self.side[topic] = pubsub.open_subscriber(self.config, topic, start="oldest")
                except FileNotFoundError:
                    pass

    def take(self, topic: str, msg: object) -> None:
        """Spool one message (and keep it in memory if it is a small stream)."""
        if msg.seq <= self.last_seq.get(topic, -1):
            return  # spooled before a restart
        self.last_seq[topic] = msg.seq
        self.health.received += 1
        arrival = msg.host_mono_ns
        self.newest[topic] = max(arrival, self.newest.get(topic, arrival))
        if topic in (LIDAR_PACKETS, LIDAR_POINTS):  # a config has one of the two
            n = self.lidar_count
            self.lidar_count += 1
            scan = scan_number(self.lidar_decoding, topic, n, msg)
            if not keeps_scan(scan, 1, self.config.mapper.inputs.lidar_every_n_scans):
                return
        with self.lock:
            self.spool.append(topic, msg, arrival)
            if topic in self.small:
                self.small[topic].append(msg)

    def _side(self, topic: str, msg: object) -> None:
        try:
            detail = json.loads(msg.detail or "{}")
        except json.JSONDecodeError:
            return
        names = [detail.get("segment")] if isinstance(detail.get("segment"), str) else []
        names += [str(p) for p in detail.get("files", []) if isinstance(p, str)]
        for name in names:
            span = self.segments.setdefault(name, [msg.host_mono_ns, msg.host_mono_ns])
            span[1] = msg.host_mono_ns

    def run(self) -> None:
        next_attach = 0.0
        while True:
            if time.monotonic() >= next_attach:
                self.attach()
                next_attach = time.monotonic() + 0.5
            got = 0
            for topic, sub in self.subs.items():
                for _ in range(64):
                    msg = sub.read(0, copy=True)
                    if msg is None:
                        break
                    got += 1
                    self.take(topic, msg)
            for topic, sub in self.side.items():
                msg = sub.read(0, copy=True)
                while msg is not None:
                    self._side(topic, msg)
                    msg = sub.read(0, copy=True)
            self.lost = sum(s.lost for s in self.subs.values())
            now = time.monotonic_ns()
            if got:
                self.last_message_ns = now
                with self.lock:
                    self.spool.flush()
            elif self.stop_requested.is_set() and now - self.last_message_ns > DRAIN_QUIET_S * 1e9:
                break
            else:
                time.sleep(0.01)
        with self.lock:
            self.spool.flush_close()
        for sub in list(self.subs.values()) + list(self.side.values()):
            sub.close()
        self.drained.set()

    def prune(self, before_ns: int) -> None:
        with self.lock:
            for topic, msgs in self.small.items():
                if topic != TIME_ANCHOR:
                    self.small[topic] = [m for m in msgs if m.host_mono_ns >= before_ns]
            self.spool.prune_before(before_ns)

    def complete_until(self, host_ns: int) -> bool:
        """Whether every topic heard from has delivered its messages up to `host_ns` (each topic arrives in
        host-time order); a topic stalled far behind the others is not waited for."""
        newest = dict(self.newest)
        if not newest:
            return False
        top = max(newest.values())
        return all(t >= host_ns or t < top - STALLED_TOPIC_NS for t in newest.values())

    def small_copy(self) -> dict[str, list]:
        with self.lock:
            return {t: list(v) for t, v in self.small.items()}
