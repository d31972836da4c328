"""Live mode: plays a simulated drive log (made by `roadlog simulate`) into virtual devices at its real
rate, for the drivers and the daemon to read as if the car were driving: Lidar packets (and the Lidar's
IMU as LEGACY IMU packets, to its own port) as UDP datagrams to 127.0.0.1, GNSS/IMU as NMEA + UBX bytes
into a pseudo-terminal, CAN frames onto a python-can bus (udp_multicast crosses processes). Cameras play
the same log through the `sim` camera backend; give it the same `start_mono_ns` and log origin to stay
in step.

Each record is sent when host monotonic time reaches start_mono_ns + (log time - log_origin_ns) / rate.
`passes` > 1 (or 0: until stopped) plays the drive again and again, an endless drive for soaks
(sim/drive_loop.py): pass k's sensor times k drive lengths later, its Lidar frame ids k passes' frames on.
The GNSS bytes are remade from the logged fixes and IMU samples (sim/sensors/gnss_sim.py, imu_sim.py):
RMC, GGA, GST and NAV-PVT per fix (velocity from consecutive fixes), one ESF-RAW per IMU sample.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import socket
import sys
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from daemon.log_format.reader import read_log, read_metadata
from daemon.spine.config import CarConfig, load_config, resolve_path
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import CanFrame, GnssFix, GnssVelocity, ImuSample, LidarPacket
from daemon.spine.topics import CAN_FRAMES, GNSS_FIX, GNSS_VELOCITY, IMU, LIDAR_IMU, LIDAR_PACKETS
from drivers.can.can_bus import open_can_bus
from drivers.lidar.ouster_encoder import packet_frame_id, renumbered_packet
from drivers.lidar.ouster_imu import encode_imu_packet
from drivers.lidar.ouster_metadata import imu_port, parse_metadata
from drivers.lidar.ouster_packet_layout import OusterPacketLayout, packet_layout
from sim.drive_loop import loop_period_ns
from sim.sensors import gnss_sim, imu_sim
from sim.sensors.sensor_clocks import ESF_TICK_NS

LATE_NS = 50_000_000
RTK_SIGMA_M = 0.05


@dataclass
class LiveDriveStats:
    lidar_packets: int = 0
    lidar_imu_packets: int = 0
    gnss_fixes: int = 0
    imu_samples: int = 0
    can_frames: int = 0
    gnss_bytes: int = 0
    gnss_dropped_bytes: int = 0  # the pseudo-terminal was full: nobody is reading the receiver
    gnss_fixes_cut: int = 0  # fixes (of gnss_fixes) whose bytes did not all fit into the pseudo-terminal
    imu_samples_cut: int = 0  # IMU samples (of imu_samples) likewise
    late: int = 0  # records sent more than LATE_NS after their moment
    passes: int = 0  # passes of the drive played to their end
    errors: int = 0
    last_error: str = ""


@dataclass
class GnssPty:
    """A pseudo-terminal: the simulator writes the receiver's bytes to `master_fd`, a driver opens `path`."""

    master_fd: int
    slave_fd: int
    path: str

    def close(self) -> None:
        os.close(self.master_fd)
        os.close(self.slave_fd)


def open_gnss_pty() -> GnssPty:
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return GnssPty(master, slave, os.ttyname(slave))


class _GnssBytes:
    """Remakes the receiver's byte stream from logged fixes, velocities and IMU samples (a fix's velocity: the one
    logged for its epoch, else the difference of the last two fixes)."""

    def __init__(self, velocities: dict[int, GnssVelocity]) -> None:
        self._frame: LocalFrame | None = None
        self._last: tuple[int, np.ndarray] | None = None
        self._velocities = velocities  # by the epoch's sensor time in ms (of the drive's first pass)
        self.shift_ns = 0  # this pass's sensor time shift

    def fix(self, fix: GnssFix) -> bytes:
        if self._frame is None:
            self._frame = LocalFrame(fix.latitude_deg, fix.longitude_deg, fix.altitude_m)
        enu = self._frame.geodetic_to_enu(fix.latitude_deg, fix.longitude_deg, fix.altitude_m)
        velocity, s_acc = np.zeros(3), 0.05
        logged = self._velocities.get(round((fix.sensor_time_ns - self.shift_ns) / 1e6))
        if logged is not None:
            velocity, s_acc = np.array(logged.velocity_enu_mps), float(np.sqrt(max(logged.velocity_covariance[0], 0)))
        elif self._last is not None and fix.sensor_time_ns > self._last[0]:
            velocity = (enu - self._last[1]) / ((fix.sensor_time_ns - self._last[0]) / 1e9)
        self._last = (fix.sensor_time_ns, enu)
        cov = fix.position_covariance
        h_acc = float(np.sqrt(max(cov[0], cov[4], 1e-6)))
        v_acc = float(np.sqrt(max(cov[8], 1e-6)))
        epoch = gnss_sim.GnssEpoch(fix.sensor_time_ns, fix.latitude_deg, fix.longitude_deg, fix.altitude_m,
                                   tuple(map(float, velocity)), h_acc, v_acc, h_acc < RTK_SIGMA_M, s_acc_m_s=s_acc)
        return gnss_sim.epoch_bytes(epoch)

    @staticmethod
    def imu(sample: ImuSample) -> bytes:
        tick = round(sample.sensor_time_ns / ESF_TICK_NS)
        return imu_sim.esf_raw_bytes(np.array(sample.accel_mps2), np.array(sample.gyro_rps), tick)


def log_origin(drive_mcap: Path) -> int:
    """The host monotonic time at which the simulated drive started (its log's start_mono_ns)."""
    meta = read_metadata(drive_mcap).get("roadlog", {})
    return int(meta.get("start_mono_ns", 0))


def run_live_drive(drive_mcap: Path, *, lidar_address: tuple[str, int] | None = None, gnss_fd: int | None = None,
                   can_bus: can.BusABC | None = None, stop: threading.Event | None = None, rate: float = 1.0,
                   start_mono_ns: int | None = None, log_origin_ns: int | None = None,
                   lidar_imu_address: tuple[str, int] | None = None, passes: int = 1,
                   lidar_layout: OusterPacketLayout | None = None) -> LiveDriveStats:
    """Play the drive into the given devices (None leaves that sensor out) `passes` times (0: until `stop`), or
    until `stop`. Looping Lidar packets needs their `lidar_layout` (to carry the frame ids on)."""
    stop = stop or threading.Event()
    start = time.monotonic_ns() if start_mono_ns is None else start_mono_ns
    origin = log_origin(drive_mcap) if log_origin_ns is None else log_origin_ns
    period_ns = loop_period_ns(drive_mcap) if passes != 1 else 0
    if passes != 1 and lidar_address is not None and lidar_layout is None:
        raise ValueError("looping a drive's Lidar packets needs their packet layout (lidar_layout)")
    topics = [t for t, on in ((LIDAR_PACKETS, lidar_address), (LIDAR_IMU, lidar_imu_address), (GNSS_FIX, gnss_fd),
                              (IMU, gnss_fd), (CAN_FRAMES, can_bus)) if on is not None]
    stats = LiveDriveStats()
    velocities = {round(rec.message.sensor_time_ns / 1e6): rec.message
                  for rec in read_log([drive_mcap], topics=[GNSS_VELOCITY])} if gnss_fd is not None else {}
    gnss = _GnssBytes(velocities)
    udp = lidar_address is not None or lidar_imu_address is not None
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if udp else None
    frame_ids: set[int] = set()  # the first pass's, to number the next passes' frames on
    try:
        for k in range(passes) if passes else itertools.count():
            shift = _PassShift(k * period_ns, k * len(frame_ids), lidar_layout)
            gnss.shift_ns = shift.time_ns
            for record in read_log([drive_mcap], topics=topics):
                due = start + int((record.log_time_ns + shift.time_ns - origin) / rate)
                while (wait := due - time.monotonic_ns()) > 0:
                    if stop.wait(min(wait / 1e9, 0.05)):
                        return stats
                if stop.is_set():
                    return stats
                if time.monotonic_ns() - due > LATE_NS:
                    stats.late += 1
                message = record.message
                if k == 0 and passes != 1 and isinstance(message, LidarPacket):
                    frame_ids.add(packet_frame_id(bytes(message.data), lidar_layout))
                try:
                    _send(record.topic, shift.applied(message), sock, lidar_address, lidar_imu_address, gnss_fd,
                          can_bus, gnss, stats)
                except (OSError, can.CanError) as exc:
                    stats.errors += 1
                    stats.last_error = f"{record.topic}: {exc}"
            stats.passes += 1
    finally:
        if sock is not None:
            sock.close()
    return stats


@dataclass(frozen=True)
class _PassShift:
    """What pass k of a looped drive changes in a record: its sensor time, and a Lidar packet's frame ids."""

    time_ns: int
    frames: int
    layout: OusterPacketLayout | None

    def applied(self, message: object) -> object:
        if self.time_ns == 0:
            return message
        if isinstance(message, LidarPacket):
            return dataclasses.replace(message, data=renumbered_packet(bytes(message.data), self.layout, self.frames,
                                                                       self.time_ns))
        if isinstance(message, (GnssFix, ImuSample)):
            return dataclasses.replace(message, sensor_time_ns=message.sensor_time_ns + self.time_ns)
        return message


def _send(topic: str, message: object, sock, lidar_address, lidar_imu_address, gnss_fd, can_bus, gnss: _GnssBytes,
          stats: LiveDriveStats) -> None:
    if topic == LIDAR_IMU:  # an ImuSample too: the topic tells the Lidar's from the GNSS receiver's
        sock.sendto(encode_imu_packet(message), lidar_imu_address)
        stats.lidar_imu_packets += 1
    elif isinstance(message, LidarPacket):
        sock.sendto(bytes(message.data), lidar_address)
        stats.lidar_packets += 1
    elif isinstance(message, GnssFix):
        stats.gnss_fixes_cut += not _write_serial(gnss_fd, gnss.fix(message), stats)
        stats.gnss_fixes += 1
    elif isinstance(message, ImuSample):
        stats.imu_samples_cut += not _write_serial(gnss_fd, gnss.imu(message), stats)
        stats.imu_samples += 1
    elif isinstance(message, CanFrame) and not message.is_error_frame:
        can_bus.send(can.Message(arbitration_id=message.arbitration_id, is_extended_id=message.is_extended_id,
                                 is_remote_frame=message.is_remote_frame, data=bytes(message.data)))
        stats.can_frames += 1


def _write_serial(fd: int, data: bytes, stats: LiveDriveStats) -> bool:
    """Write one message's bytes into the pseudo-terminal; whether they all went in (a full one drops the rest, as
    a serial line overruns when nobody reads it)."""
    try:
        written = os.write(fd, data)
    except BlockingIOError:
        written = 0
    stats.gnss_bytes += written
    stats.gnss_dropped_bytes += len(data) - written
    return written == len(data)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.live_drive", description=__doc__.split("\n\n")[0])
    parser.add_argument("--drive", required=True, type=Path, help="a drive log made by `roadlog simulate`")
    parser.add_argument("--config", type=Path, default=Path(__file__).resolve().parents[1] / "configs" / "sim.yaml")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed (1 = real time)")
    parser.add_argument("--passes", type=int, default=1, help="play the drive this many times (0: until stopped)")
    args = parser.parse_args(argv)
    config: CarConfig = load_config(args.config)
    sensors = config.sensors
    pty = open_gnss_pty() if sensors.gnss is not None else None
    bus = open_can_bus(sensors.can) if sensors.can is not None else None
    lidar = ("127.0.0.1", sensors.lidar.port) if sensors.lidar is not None else None
    metadata = None if sensors.lidar is None else parse_metadata(resolve_path(args.config, sensors.lidar.metadata_file))
    port = None if sensors.lidar is None else imu_port(sensors.lidar, metadata)
    lidar_imu = ("127.0.0.1", port) if port else None
    if pty is not None:
        print(f"GNSS pseudo-terminal: {pty.path}", flush=True)
    try:
        stats = run_live_drive(args.drive, lidar_address=lidar, gnss_fd=pty.master_fd if pty else None,
                               can_bus=bus, rate=args.rate, lidar_imu_address=lidar_imu, passes=args.passes,
                               lidar_layout=None if metadata is None else packet_layout(metadata))
    except KeyboardInterrupt:
        return 130
    finally:
        if bus is not None:
            bus.shutdown()
        if pty is not None:
            pty.close()
    print(stats)
    return 1 if stats.errors else 0


if __name__ == "__main__":
    sys.exit(main())
