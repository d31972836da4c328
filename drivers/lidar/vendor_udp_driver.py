"""The Lidar driver process for every vendor but Ouster (Velodyne, Hesai, RoboSense): each UDP datagram that is one
of the configured sensor's data packets goes to `lidar/packets`, as received, stamped on the sensor's clock.

Datagrams are received in batches (drivers.lidar.udp_receive) and looked at by the model's decoder without
decoding their points (`PacketDecoder.check`): anything else (a position or device-info packet on the same port,
another sensor's, a truncated or malformed one) is counted by reason and not published. A Velodyne stamps its
packets in microseconds past the top of the hour: the stamps are unwrapped into one continuous sensor time, placed
in the hour the host clock is in (exact when the sensor is GPS-synchronised, consistent when not). A jump of the
stamps forwards by more than `GAP_ROTATIONS` rotation periods is counted as a gap (packets lost before the socket).
A sensor whose packets carry its IMU's readings (the Pandar128E4X) has each new reading published on `lidar/imu`."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from daemon.spine.config import CarConfig, ConfigError, LidarConfig, load_config, reports_config_errors
from daemon.spine.health import HealthCounters
from daemon.spine.messages import ImuSample, LidarPacket
from daemon.spine.process_logging import setup_logging
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import LIDAR_IMU, LIDAR_PACKETS, health_topic
from drivers.lidar.lidar_models import VENDOR_LIDARS, configured_decoder
from drivers.lidar.packet_decoding import PacketDecoder
from drivers.lidar.udp_receive import ReceiveBuffer, open_lidar_socket, report_short_buffer, serve_batches

PROCESS = "lidar"
log = logging.getLogger(__name__)
ROW_BYTES = 1500  # an Ethernet frame's payload at most: every vendor's data packet fits; larger ones are rejected
GAP_ROTATIONS = 0.5  # a stamp this many rotation periods after the last one means packets were lost

Publish = Callable[[str, object], None]


@dataclass
class VendorDriverStats:
    """What the driver saw, beyond the generic health counters."""

    model: str = ""
    receive_buffer_bytes: int = 0  # SO_RCVBUF the kernel granted
    datagrams: int = 0
    packets: int = 0  # published
    too_large: int = 0  # datagrams beyond ROW_BYTES (also in rejected, by the decoder's reason for an empty one)
    rejected: dict[str, int] = field(default_factory=dict)  # the decoder's reason -> datagrams not published
    imu_samples: int = 0  # published on lidar/imu (a sensor whose packets carry its IMU's readings)
    gaps: int = 0
    stamps_back: int = 0  # packets stamped earlier than the one before (a reordered or restarted stream)
    kernel_drops: int = 0
    socket_errors: int = 0
    batches: int = 0

    def summary(self) -> str:
        return " ".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self))


@dataclass
class StampClock:
    """Packet stamps that count modulo `period_ns` (None: absolute) unwrapped into one continuous sensor time."""

    period_ns: int | None
    last_stamp: int | None = None
    last_time: int | None = None

    def times(self, stamps: np.ndarray, host_real_ns: int) -> np.ndarray:
        """Sensor times of consecutive packet stamps: each is the previous time plus the stamp difference taken
        within half a period either way (the first in the period nearest the host's real time)."""
        stamps = np.asarray(stamps, dtype=np.int64)
        if self.period_ns is None or len(stamps) == 0:
            return stamps
        p = self.period_ns
        if self.last_stamp is None:
            first = int(stamps[0]) + round((host_real_ns - int(stamps[0])) / p) * p
            self.last_stamp, self.last_time = int(stamps[0]), first
        steps = np.diff(np.concatenate([[self.last_stamp], stamps]))
        steps = (steps + p // 2) % p - p // 2
        times = self.last_time + np.cumsum(steps)
        self.last_stamp, self.last_time = int(stamps[-1]), int(times[-1])
        return times


def _publish_health(publish: Publish, health: HealthCounters, stats: VendorDriverStats) -> None:
    detail = stats.summary() + (f"; last error: {health.last_error}" if health.last_error else "")
    publish(health_topic(PROCESS), dataclasses.replace(health.snapshot(), detail=detail))


@dataclass
class PacketImu:
    """The IMU readings in a sensor's data packets (VendorLidar.imu_readings), each published once on lidar/imu."""

    readings: Callable[[list[bytes]], dict[str, np.ndarray]]
    last_counter: int | None = None  # the IMU's own counter of the last reading published

    def publish_new(self, payloads: list[bytes], stamps: np.ndarray, times: np.ndarray, arrivals: np.ndarray,
                    publish: Publish, stats: VendorDriverStats) -> None:
        """The readings of these accepted packets (their own stamps, the sensor times they were published at, their
        arrivals) that were not published yet, each at the time and arrival of the packet it came in."""
        got = self.readings(payloads)
        counter = got["imu_timestamp"]
        fresh = np.ones(len(counter), bool)
        if len(counter) and self.last_counter is not None:
            fresh[0] = int(counter[0]) != self.last_counter  # the batch before published it
        packet = np.minimum(np.searchsorted(stamps, got["time_ns"]), len(stamps) - 1)
        for k in np.flatnonzero(fresh):
            i = int(packet[k])
            publish(LIDAR_IMU, ImuSample(sensor_time_ns=int(times[i]), host_mono_ns=int(arrivals[i]),
                                         accel_mps2=tuple(float(v) for v in got["linear_acceleration_m_s2"][k]),
                                         gyro_rps=tuple(float(v) for v in got["angular_velocity_rad_s"][k])))
            stats.imu_samples += 1
        if len(counter):
            self.last_counter = int(counter[-1])


def _handle_batch(buf: ReceiveBuffer, n: int, decoder: PacketDecoder, clock: StampClock, rotation_ns: int,
                  imu: PacketImu | None, publish: Publish, health: HealthCounters, stats: VendorDriverStats) -> None:
    """Check one batch, publish its packets in arrival order, count the rest and the gaps."""
    sizes = buf.sizes[:n]
    fits = sizes <= ROW_BYTES
    payloads = [buf.rows[i, :sizes[i]].tobytes() if fits[i] else b"" for i in range(n)]
    check = decoder.check(payloads)
    accepted = check.accepted & fits
    stats.batches += 1
    stats.datagrams += n
    health.received += n
    stats.too_large += int((~fits).sum())  # given to the decoder empty: it counts them as of the wrong size
    for reason, count in check.counts.items():
        stats.rejected[reason] = stats.rejected.get(reason, 0) + count
    rejected = n - int(accepted.sum())
    health.rejected += rejected
    if rejected:
        first = int(np.flatnonzero(~accepted)[0])
        health.last_error = (f"{rejected} datagram(s) not {decoder.model} data packets "
                             f"({', '.join(f'{k}={v}' for k, v in sorted(check.counts.items()))}), first: "
                             f"{sizes[first]} B {payloads[first][:8].hex()}...")
    index = np.flatnonzero(accepted)
    if not len(index):
        return
    previous = clock.last_time
    times = clock.times(check.sensor_time_ns[index], time.time_ns())
    steps = np.diff(np.concatenate([[previous if previous is not None else times[0]], times]))
    stats.gaps += int((steps > GAP_ROTATIONS * rotation_ns).sum())
    stats.stamps_back += int((steps < 0).sum())
    health.sequence_gaps = stats.gaps
    for i, t in zip(index.tolist(), times.tolist(), strict=True):
        publish(LIDAR_PACKETS, LidarPacket(sensor_time_ns=t, host_mono_ns=int(buf.arrival_ns[i]), data=payloads[i]))
    health.count_published(len(index))
    stats.packets += len(index)
    if imu is not None:
        imu.publish_new([payloads[i] for i in index], check.sensor_time_ns[index], times, buf.arrival_ns[index],
                        publish, stats)


def run_vendor_lidar_driver(
    config: LidarConfig,
    decoder: PacketDecoder,
    publish: Publish,
    stop: threading.Event,
    health: HealthCounters,
    *,
    batch_packets: int = 256,
    batch_period_s: float = 0.01,
    health_period_s: float = 1.0,
    idle_wait_s: float = 0.1,
) -> VendorDriverStats:
    """Receive, check and publish packets until `stop` is set; health goes out once listening, then every
    `health_period_s`. Raises OSError when the socket cannot be bound."""
    sock, granted = open_lidar_socket(config.bind_address, config.port, config.receive_buffer_bytes)
    stats = VendorDriverStats(model=decoder.model, receive_buffer_bytes=granted)
    report_short_buffer(granted, config.receive_buffer_bytes, health)
    lidar = VENDOR_LIDARS[config.model]
    clock = StampClock(lidar.stamp_period_ns)
    imu = PacketImu(lidar.imu_readings) if lidar.imu_readings is not None else None
    rotation_ns = round(1e9 / config.rate_hz)
    buf = ReceiveBuffer.allocate(batch_packets, ROW_BYTES)
    try:
        serve_batches(sock, buf, batch_period_s,
                      lambda n: _handle_batch(buf, n, decoder, clock, rotation_ns, imu, publish, health, stats),
                      lambda: _publish_health(publish, health, stats), stop, stats, health, health_period_s,
                      idle_wait_s)
    finally:
        sock.close()
    _publish_health(publish, health, stats)
    return stats


def check_config(car: CarConfig, config_path: str | Path) -> PacketDecoder:
    """What the driver checks before it starts (also run by `roadlog check-config`): the calibration file reads and
    fits the model."""
    if car.sensors.lidar is None:
        raise ConfigError(f"{config_path}: has no sensors.lidar section")
    return configured_decoder(car.sensors.lidar, config_path)


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="roadlog Lidar driver: raw Velodyne/Hesai/RoboSense UDP packets "
                                                 "onto the bus")
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--port", type=int, help="override sensors.lidar.port")
    parser.add_argument("--bind", help="override sensors.lidar.bind_address")
    args = parser.parse_args(argv)
    setup_logging(PROCESS)

    from daemon.bus.pubsub import open_publisher

    car = load_config(args.config)
    decoder = check_config(car, args.config)
    overrides = {k: v for k, v in (("port", args.port), ("bind_address", args.bind)) if v is not None}
    config = car.sensors.lidar.model_copy(update=overrides)
    publishers = {topic: open_publisher(car, topic) for topic in (LIDAR_PACKETS, LIDAR_IMU, health_topic(PROCESS))}
    health = HealthCounters(PROCESS)
    stop = threading.Event()
    set_on_signals(stop)
    try:
        stats = run_vendor_lidar_driver(config, decoder, lambda topic, m: publishers[topic].publish(m), stop, health)
    except OSError as exc:
        log.error("%s", exc.strerror or exc)
        return 1
    print(f"lidar driver stopped ({decoder.model}): {stats.summary()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
