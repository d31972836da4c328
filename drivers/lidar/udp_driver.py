"""The Lidar driver process: every Ouster UDP packet that holds together goes to `lidar/packets`, as received.

Datagrams are received in batches (wait for the first, let more gather for `batch_period_s`) into one
(N, packet size) buffer, each with its kernel arrival time, and decoded together
(`drivers.lidar.ouster_decoder`) to validate them and follow the sensor's own packet numbering
(frame id, measurement id). A datagram of the wrong size or whose header does not hold together is
counted as rejected and not published: it is not sensor data. Packets missing from the numbering
are counted as dropped, each run of them as one sequence gap; a jump too large to be a loss is
taken as a sensor restart. Pixels are not looked at here (no point clouds in this process), so that
it keeps up with the socket. Only Ouster sensors have a decoder.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.spine.config import CarConfig, ConfigError, LidarConfig, load_config, reports_config_errors
from daemon.spine.health import HealthCounters
from daemon.spine.messages import LidarPacket
from daemon.spine.process_logging import setup_logging
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import LIDAR_IMU, LIDAR_PACKETS, health_topic
from drivers.lidar.ouster_decoder import count_missing_packets, decode_packets, newest_packet, packet_sequence
from drivers.lidar.ouster_imu import decode_imu_packet, imu_profile_supported
from drivers.lidar.ouster_metadata import OusterMetadata, configured_metadata, imu_port
from drivers.lidar.ouster_packet_layout import OusterPacketLayout, packet_layout, packets_per_second
from drivers.lidar.udp_receive import (
    ReceiveBuffer,
    open_lidar_socket,
    receive_queued,
    report_short_buffer,
    serve_batches,
)

PROCESS = "lidar"
log = logging.getLogger(__name__)
RESTART_AFTER_S = 60.0  # a numbering jump of more than this many seconds of packets is a sensor restart
IMU_RECEIVE_BUFFER_BYTES = 1 << 20  # ~20,000 LEGACY IMU packets: 200 s at 100 Hz
IMU_BATCH = 64  # IMU datagrams taken from the socket at once
IMU_ROW_BYTES = 512  # larger datagrams are rejected by their real size (MSG_TRUNC)

Publish = Callable[[str, object], None]


@dataclass
class LidarDriverStats:
    """What the driver saw, beyond the generic health counters."""

    receive_buffer_bytes: int = 0  # SO_RCVBUF the kernel granted (it doubles what was asked, then caps)
    batch_period_ms: float = 0.0
    datagrams: int = 0
    packets: int = 0  # published
    wrong_size: int = 0
    bad_header: int = 0
    invalid_columns: int = 0  # columns the sensor flagged as holding no data, in published packets
    missing_packets: int = 0
    gaps: int = 0
    restarts: int = 0
    kernel_drops: int = 0  # the socket's overflow count (SO_RXQ_OVFL), as last reported by the kernel
    socket_errors: int = 0
    batches: int = 0
    largest_batch: int = 0
    imu: str = "off"  # "listening on PORT", "off", or why not
    imu_samples: int = 0  # published on lidar/imu
    imu_rejected: int = 0  # IMU datagrams of the wrong size or with values that are not numbers
    imu_kernel_drops: int = 0

    def summary(self) -> str:
        return " ".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self))


@dataclass
class PacketLossCounter:
    """Packets missing from the sensor's packet numbering (see ouster_decoder.packet_sequence), across batches."""

    layout: OusterPacketLayout
    restart_after_packets: int
    newest: int | None = None
    missing: int = 0
    gaps: int = 0
    restarts: int = 0

    def _ahead(self, sequence: np.ndarray, reference: int) -> np.ndarray:
        modulus = self.layout.frame_id_modulus * self.layout.window_packets[1]
        step = (sequence - reference) % modulus
        return np.where(step > modulus // 2, step - modulus, step)

    def add(self, sequence: np.ndarray) -> int | None:
        """Count the losses up to this batch's newest packet; returns the jump (packets) when the
        numbering restarted instead."""
        if len(sequence) == 0:
            return None
        jump = None
        if self.newest is not None:
            furthest = int(self._ahead(sequence, self.newest).max())
            if furthest > self.restart_after_packets or furthest < -self.layout.window_packets[1]:
                self.restarts += 1
                self.newest, jump = None, furthest
        reference = int(sequence[0]) if self.newest is None else self.newest
        ahead = np.unique(self._ahead(sequence, reference))
        self.gaps += int(np.count_nonzero(np.diff(ahead[ahead > 0], prepend=0) > 1))
        self.missing += count_missing_packets(sequence, self.layout, self.newest)
        self.newest = newest_packet(sequence, self.layout, self.newest)
        return jump


def _count_rejects(buf: ReceiveBuffer, n: int, accepted: np.ndarray, layout: OusterPacketLayout,
                   wrong_size: int, bad_header: int, health: HealthCounters) -> None:
    health.rejected += wrong_size + bad_header
    if wrong_size:
        sizes = buf.sizes[:n][buf.sizes[:n] != layout.packet_size]
        health.last_error = (f"{wrong_size} datagram(s) of the wrong size ({sizes[0]} B; a {layout.profile} "
                             f"packet is {layout.packet_size} B)")
    if bad_header:
        right_size = np.flatnonzero(buf.sizes[:n] == layout.packet_size)
        first = np.setdiff1d(right_size, accepted)[0]
        health.last_error = (f"{bad_header} packet(s) with a bad header (packet type, serial number, frame or "
                             f"measurement ids), first: {bytes(buf.rows[first, :16]).hex()}...")


def _handle_batch(buf: ReceiveBuffer, n: int, layout: OusterPacketLayout, prod_sn: int | None, publish: Publish,
                  health: HealthCounters, stats: LidarDriverStats, loss: PacketLossCounter) -> None:
    """Decode one batch, publish its good packets in arrival order, count the rest and the losses."""
    batch = decode_packets(buf.rows[:n], layout, sizes=buf.sizes[:n], prod_sn=prod_sn)
    counts = batch.counts
    stats.batches += 1
    stats.largest_batch = max(stats.largest_batch, n)
    stats.datagrams += n
    stats.wrong_size += counts.wrong_size
    stats.bad_header += counts.bad_header
    stats.invalid_columns += counts.invalid_columns
    health.received += n
    if counts.wrong_size or counts.bad_header:
        _count_rejects(buf, n, batch.packet_index, layout, counts.wrong_size, counts.bad_header, health)
    p = batch.num_packets
    if p == 0:
        return
    first_valid = np.argmax(batch.column_valid, axis=1)
    sensor_ns = np.where(batch.column_valid.any(axis=1), batch.timestamp_ns[np.arange(p), first_valid], 0)
    for i, t in zip(batch.packet_index.tolist(), sensor_ns.tolist(), strict=True):
        publish(LIDAR_PACKETS, LidarPacket(sensor_time_ns=t, host_mono_ns=int(buf.arrival_ns[i]),
                                           data=buf.rows[i].tobytes()))
    health.count_published(p)
    stats.packets += p
    jump = loss.add(packet_sequence(batch, layout))
    if jump is not None:
        health.count_error(f"packet numbering jumped by {jump} packets: sensor restarted, counting anew")
    stats.missing_packets, stats.gaps, stats.restarts = loss.missing, loss.gaps, loss.restarts
    health.dropped, health.sequence_gaps = loss.missing, loss.gaps


def _open_imu_socket(config: LidarConfig, metadata: OusterMetadata, stats: LidarDriverStats,
                     health: HealthCounters) -> socket.socket | None:
    """The IMU's socket, or None (off, an IMU profile without a decoder, or the port cannot be bound: the
    Lidar is recorded all the same, and the reason is reported)."""
    port = imu_port(config, metadata)
    if port is None:
        return None
    if not imu_profile_supported(metadata.udp_profile_imu):
        stats.imu = f"not decoded: IMU profile {metadata.udp_profile_imu}"
        health.last_error = f"IMU packets not recorded: profile {metadata.udp_profile_imu} has no decoder"
        return None
    try:
        sock, _ = open_lidar_socket(config.bind_address, port, IMU_RECEIVE_BUFFER_BYTES)
    except OSError as exc:
        stats.imu = f"not listening: {exc.strerror}"
        health.count_error(f"IMU packets not recorded: {exc.strerror}")
        return None
    stats.imu = f"listening on {port}"
    return sock


def _handle_imu(sock: socket.socket, buf: ReceiveBuffer, publish: Publish, stats: LidarDriverStats,
                health: HealthCounters) -> None:
    """Publish the IMU packets queued on `sock`; count and report the ones that do not decode."""
    seen = LidarDriverStats()  # this socket's own overflow count and errors
    n = receive_queued(sock, buf, 0, time.monotonic_ns() - time.time_ns(), seen, health)
    stats.imu_kernel_drops = seen.kernel_drops
    stats.socket_errors += seen.socket_errors
    for i in range(n):
        try:  # the row holds at most IMU_ROW_BYTES of the datagram; its real length is in sizes
            sample = decode_imu_packet(buf.rows[i, :buf.sizes[i]].tobytes(), int(buf.arrival_ns[i]),
                                       size=int(buf.sizes[i]))
        except ValueError as exc:
            stats.imu_rejected += 1
            health.rejected += 1
            health.last_error = str(exc)
            continue
        publish(LIDAR_IMU, sample)
        stats.imu_samples += 1


def _publish_health(publish: Publish, health: HealthCounters, stats: LidarDriverStats) -> None:
    snap = health.snapshot()
    detail = stats.summary() + (f"; last error: {health.last_error}" if health.last_error else "")
    publish(health_topic(PROCESS), dataclasses.replace(snap, detail=detail))


def batch_period(receive_buffer_bytes: int, layout: OusterPacketLayout, packets_per_s: float,
                 longest_s: float) -> float:
    """How long to let datagrams gather: at most a quarter of the time the receive buffer takes to fill
    at the sensor's rate, taking each datagram to cost the kernel twice its size (a reassembled or
    loopback datagram costs up to a power of two above its size)."""
    fill_s = receive_buffer_bytes / (2 * layout.packet_size) / packets_per_s
    return min(longest_s, fill_s / 4)


def run_lidar_driver(
    config: LidarConfig,
    metadata: OusterMetadata,
    publish: Publish,
    stop: threading.Event,
    health: HealthCounters,
    *,
    batch_packets: int = 256,
    batch_period_s: float = 0.02,
    health_period_s: float = 1.0,
    idle_wait_s: float = 0.1,
) -> LidarDriverStats:
    """Receive, validate and publish packets until `stop` is set. Datagrams gather for up to
    `batch_period_s` (less when the granted receive buffer is small, see batch_period) or until
    `batch_packets` arrived. Health goes out once listening, then every `health_period_s`. Raises
    OSError when the socket cannot be bound."""
    layout = packet_layout(metadata)
    prod_sn = int(metadata.prod_sn) if metadata.prod_sn.isdigit() else None
    sock, granted = open_lidar_socket(config.bind_address, config.port, config.receive_buffer_bytes)
    rate = packets_per_second(metadata)
    period_s = batch_period(granted, layout, rate, batch_period_s)
    stats = LidarDriverStats(receive_buffer_bytes=granted, batch_period_ms=round(1000 * period_s, 3))
    report_short_buffer(granted, config.receive_buffer_bytes, health)
    loss = PacketLossCounter(layout, round(RESTART_AFTER_S * rate))
    buf = ReceiveBuffer.allocate(batch_packets, layout.packet_size)
    imu_sock = _open_imu_socket(config, metadata, stats, health)
    imu_buf = ReceiveBuffer.allocate(IMU_BATCH, IMU_ROW_BYTES)
    others = {} if imu_sock is None else {imu_sock: lambda: _handle_imu(imu_sock, imu_buf, publish, stats, health)}
    try:
        serve_batches(sock, buf, period_s,
                      lambda n: _handle_batch(buf, n, layout, prod_sn, publish, health, stats, loss),
                      lambda: _publish_health(publish, health, stats), stop, stats, health, health_period_s,
                      idle_wait_s, others)
    finally:
        sock.close()
        if imu_sock is not None:
            imu_sock.close()
    _publish_health(publish, health, stats)
    return stats


def check_config(car: CarConfig, config_path: str | Path) -> tuple[OusterMetadata, OusterPacketLayout]:
    """What the driver checks before it starts (also run by `roadlog check-config`): the sensor metadata file
    reads and gives a packet layout the decoder knows."""
    if car.sensors.lidar is None:
        raise ConfigError(f"{config_path}: has no sensors.lidar section")
    metadata = configured_metadata(car.sensors.lidar, config_path)
    try:
        return metadata, packet_layout(metadata)
    except ValueError as exc:
        raise ConfigError(f"{config_path}: sensors.lidar.metadata_file {car.sensors.lidar.metadata_file!r}: "
                          f"{exc}") from None


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="roadlog Lidar driver: raw Ouster UDP packets onto the bus")
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--port", type=int, help="override sensors.lidar.port")
    parser.add_argument("--bind", help="override sensors.lidar.bind_address")
    args = parser.parse_args(argv)
    setup_logging(PROCESS)

    from daemon.bus.pubsub import open_publisher

    car = load_config(args.config)
    metadata, layout = check_config(car, args.config)
    overrides = {k: v for k, v in (("port", args.port), ("bind_address", args.bind)) if v is not None}
    config = car.sensors.lidar.model_copy(update=overrides)
    if metadata.columns_per_frame != config.columns_per_frame or metadata.fps != config.rate_hz:
        log.warning("the sensor metadata says %s, the config %sx%s; decoding as the metadata says",
                    metadata.lidar_mode, config.columns_per_frame, config.rate_hz)
    publishers = {topic: open_publisher(car, topic) for topic in (LIDAR_PACKETS, LIDAR_IMU, health_topic(PROCESS))}
    health = HealthCounters(PROCESS, expected_rate_hz=packets_per_second(metadata))
    stop = threading.Event()
    set_on_signals(stop)
    try:
        stats = run_lidar_driver(config, metadata, lambda topic, m: publishers[topic].publish(m), stop, health)
    except OSError as exc:
        log.error("%s", exc.strerror or exc)
        return 1
    print(f"lidar driver stopped ({metadata.prod_line} {layout.profile}, {layout.packet_size} B packets): "
          f"{stats.summary()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
