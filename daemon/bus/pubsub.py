"""The message bus: per-topic publishers and subscribers of message dataclasses over shared-memory rings.

Each topic of `daemon.spine.topics.topic_table` has one ring (`daemon.bus.ring_buffer`) named
`/dev/shm/<bus.shm_prefix>.<topic with "/" as ".">`, sized by the topic's `ring_bytes`. A message
travels as its protobuf meta (`message_codec.encode_split`) plus its bulk `data` bytes, which are
written straight into the ring and handed to readers as a zero-copy view.

One Publisher per topic on the whole machine (a second live one is refused; a restarted one
continues the sequence). Any number of Subscribers; each is for one thread. A lossless subscriber
keeps the data of the message it last read intact until its next `read()`.
"""

from __future__ import annotations

import glob
import os
import time

from daemon.bus.ring_buffer import RingReader, RingWriter, retire
from daemon.spine import message_codec
from daemon.spine.config import CarConfig
from daemon.spine.topics import Topic, topic_table

SHM_DIR = "/dev/shm"
_RING_WAIT_POLL_S = 0.005


def ring_path(config: CarConfig, topic_name: str) -> str:
    return os.path.join(SHM_DIR, f"{config.bus.shm_prefix}.{topic_name.replace('/', '.')}")


def _topic(config: CarConfig, topic_name: str) -> Topic:
    table = topic_table(config)
    if topic_name not in table:
        raise KeyError(f"unknown topic {topic_name!r} (known: {', '.join(sorted(table))})")
    return table[topic_name]


class Publisher:
    """The one writer of a topic."""

    def __init__(self, topic: Topic, path: str):
        self.topic = topic
        self._ring = RingWriter(path, topic.ring_bytes, label=f"topic {topic.name!r}")

    @property
    def next_seq(self) -> int:
        return self._ring.next_seq

    def publish(self, message: object, *, lossless: bool = False, timeout_s: float | None = None) -> int:
        """Send a message; sets its seq (and host_mono_ns when 0) and returns the seq.

        lossless: wait (up to timeout_s, then TimeoutError) until no registered lossless subscriber
        would be overtaken by this write.
        """
        if type(message) is not self.topic.message_type:
            raise TypeError(f"topic {self.topic.name!r} carries {self.topic.message_type.__name__}, "
                            f"not {type(message).__name__}")
        message.seq = self._ring.next_seq
        if message.host_mono_ns == 0:
            message.host_mono_ns = time.monotonic_ns()
        meta, bulk = message_codec.encode_split(message)
        return self._ring.write(meta, bulk, lossless=lossless, timeout_s=timeout_s)

    def close(self) -> None:
        self._ring.close()

    def __enter__(self) -> Publisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_publisher(config: CarConfig, topic_name: str) -> Publisher:
    """Create the topic's ring, or attach to it and continue its sequence (writer restart)."""
    return Publisher(_topic(config, topic_name), ring_path(config, topic_name))


class Subscriber:
    """One reader of a topic. `lost` counts messages overwritten before this reader got to them."""

    def __init__(self, topic: Topic, ring: RingReader):
        self.topic = topic
        self._ring = ring
        self._last = None

    @property
    def lost(self) -> int:
        return self._ring.lost

    @property
    def received(self) -> int:
        return self._ring.received

    @property
    def skipped(self) -> int:
        """Messages passed over by `latest()` (not counted as lost)."""
        return self._ring.skipped

    def _decode(self, record) -> object:
        self._last = record
        return message_codec.decode_split(self.topic.message_type, record.meta, record.bulk)

    def read(self, timeout_s: float | None = None, *, copy: bool = False) -> object | None:
        """The next message, waiting up to timeout_s (None: forever, 0: not at all); None on timeout.

        Unless copy=True, a bulk `data` field is a read-only memoryview into shared memory: check
        `still_valid()` after using it (the writer may have overwritten it if this reader fell behind).
        """
        record = self._ring.read(timeout_s, copy=copy)
        return None if record is None else self._decode(record)

    def latest(self, *, copy: bool = True) -> object | None:
        """The newest message on the topic (again, if already returned); None if there is none.

        Messages between the last one returned and the newest are skipped (counted in `skipped`)."""
        record = self._ring.latest(copy=copy)
        return None if record is None else self._decode(record)

    def still_valid(self) -> bool:
        """Whether the bulk bytes of the last message returned are still intact in shared memory."""
        return self._last is not None and self._last.still_valid()

    def backlog_bytes(self) -> int:
        return self._ring.backlog_bytes()

    def close(self) -> None:
        self._last = None
        self._ring.close()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_subscriber(config: CarConfig, topic_name: str, *, start: str = "next", lossless: bool = False,
                    wait_s: float = 0, after_seq: int | None = None) -> Subscriber:
    """Attach to a topic's ring, waiting up to wait_s for its writer to create it.

    start: "next" (new messages only), "oldest" (everything still in the ring) or "latest".
    lossless: register so that lossless publishes wait for this subscriber (while it lives).
    after_seq (with "oldest"): resume after this seq (a restarted reader; see RingReader).
    """
    topic = _topic(config, topic_name)
    path = ring_path(config, topic_name)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return Subscriber(topic, RingReader(path, start=start, lossless=lossless, after_seq=after_seq))
        except FileNotFoundError:
            if time.monotonic() >= deadline:
                raise FileNotFoundError(f"topic {topic_name!r} has no ring at {path} "
                                        f"(no writer created it within {wait_s} s)") from None
            time.sleep(_RING_WAIT_POLL_S)


def unlink_topic(config: CarConfig, topic_name: str) -> None:
    """Remove a topic's ring (readers still attached wait for a new one)."""
    retire(ring_path(config, topic_name))


def unlink_all(config: CarConfig) -> None:
    """Remove every ring of this bus prefix."""
    for path in glob.glob(os.path.join(SHM_DIR, f"{config.bus.shm_prefix}.*")):
        if ".creating." not in path:  # a writer's half-made ring, about to be linked into place
            retire(path)
