"""The live worker's bus thread: every topic the mapper needs, read losslessly into the disk spools (the small
streams, GNSS/IMU/wheels/anchors, into a spool of their own, read back for each window's fusion; of the Lidar's packets
or point clouds every n-th scan), and the log segments the recorder or player name.

What it holds in memory does not grow with how far the worker is behind: the wheel speeds not yet integrated into
the odometry (taken every second, or after a window), and the time anchors (one a second, ~100 bytes each)."""

from __future__ import annotations

import json
import threading
import time

from daemon.bus import pubsub
from daemon.spine.config import CarConfig
from daemon.spine.health import HealthCounters
from daemon.spine.topics import (
    FUSION_TOPICS,
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
SMALL_TOPICS = (*FUSION_TOPICS, TIME_ANCHOR)
SEGMENT_SOURCES = (health_topic("recorder"), health_topic("replay"))


class BusReader(threading.Thread):
    """Reads every topic the mapper needs into the spools (wheel speeds and anchors also into memory)."""

    def __init__(self, config: CarConfig, spool: KeyframeSpool, small_spool: KeyframeSpool, lock: threading.Lock,
                 health: HealthCounters, last_seq: dict[str, int],
                 lidar_decoding: OusterMetadata | VendorDecoding | None):
        super().__init__(name="mapper-bus", daemon=True)
        self.config = config
        self.spool = spool
        self.small_spool = small_spool  # GNSS, IMU, wheel speeds, anchors
        self.lock = lock
        self.health = health
        self.last_seq = last_seq
        self.wheels: list = []  # wheel speeds not yet taken by the odometry (take_wheels)
        self.anchors: list = []  # every time anchor (one a second)
        self.segments: dict[str, list[int]] = {}  # segment name -> [first, last] host ns seen open
        self.stop_requested = threading.Event()
        self.drained = threading.Event()
        cams = [c.name for c in config.sensors.cameras]
        table = topic_table(config)
        self.topics = [t for t in [camera_topic(c) for c in cams] + [mask_topic(c) for c in cams]
                       + [LIDAR_PACKETS, LIDAR_POINTS, *SMALL_TOPICS] if t in table]
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
        """Spool one message (a wheel speed also for the odometry, an anchor also in memory)."""
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
            if topic in SMALL_TOPICS:
                self.small_spool.append(topic, msg, arrival)
                if topic == WHEEL_SPEEDS:
                    self.wheels.append(msg)
                elif topic == TIME_ANCHOR:
                    self.anchors.append(msg)
            else:
                self.spool.append(topic, msg, arrival)

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
                    self.small_spool.flush()
            elif self.stop_requested.is_set() and now - self.last_message_ns > DRAIN_QUIET_S * 1e9:
                break
            else:
                time.sleep(0.01)
        with self.lock:
            self.spool.flush_close()
            self.small_spool.flush_close()
        for sub in list(self.subs.values()) + list(self.side.values()):
            sub.close()
        self.drained.set()

    def prune(self, before_ns: int) -> None:
        """Delete the spooled chunks no window from `before_ns` on needs."""
        with self.lock:
            self.spool.prune_before(before_ns)
            self.small_spool.prune_before(before_ns)

    def take_wheels(self) -> list:
        """The wheel speeds received since the last call, in arrival order."""
        with self.lock:
            wheels, self.wheels = self.wheels, []
        return wheels

    def pending_wheels(self) -> list:
        """The wheel speeds received and not yet taken (a copy: they stay for take_wheels)."""
        with self.lock:
            return list(self.wheels)

    def complete_until(self, host_ns: int) -> bool:
        """Whether every topic heard from has delivered its messages up to `host_ns` (each topic arrives in
        host-time order); a topic stalled far behind the others is not waited for."""
        newest = dict(self.newest)
        if not newest:
            return False
        top = max(newest.values())
        return all(t >= host_ns or t < top - STALLED_TOPIC_NS for t in newest.values())

    def read_small(self, first_ns: int, last_ns: int) -> dict[str, list]:
        """The GNSS fixes and velocities, IMU samples and wheel speeds that arrived in [first_ns, last_ns] (from their
        spool), and every time anchor up to last_ns."""
        small: dict[str, list] = {t: [] for t in SMALL_TOPICS}
        with self.lock:
            for _, topic, msg in self.small_spool.read(first_ns, last_ns, set(FUSION_TOPICS)):
                small[topic].append(msg)
            small[TIME_ANCHOR] = [a for a in self.anchors if a.host_mono_ns <= last_ns]
        return small

    def held(self) -> dict[str, int]:
        """What it holds in memory, by count (health)."""
        return {"wheel_speeds_pending": len(self.wheels), "time_anchors": len(self.anchors),
                "segments": len(self.segments), "spool_chunks": len(self.spool.chunks) + len(self.small_spool.chunks)}
