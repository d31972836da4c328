"""The sensor streams' fuzz cases for bench/parser_fuzz.py (`ouster_packets`, `nmea_ubx`, `can`): what each case is
made of (the shared real captures, mutated) and what its check counts beyond an uncaught exception."""

from __future__ import annotations

import math
import random
import threading
from collections import Counter
from pathlib import Path

import can

from daemon.spine.config import load_config
from daemon.spine.health import HealthCounters
from daemon.spine.messages import GnssFix, GnssVelocity
from daemon.spine.topics import CAN_FRAMES
from drivers.can.can_driver import run_can_driver
from drivers.can.wheel_speed_codec import encode_wheel_speeds, load_dbc
from drivers.gnss.gnss_messages import GnssDecoder
from drivers.gnss.stream_framer import StreamFramer
from drivers.lidar.ouster_decoder import count_missing_packets, decode_packets, ouster_scan_assembler, packet_sequence
from drivers.lidar.ouster_metadata import parse_metadata
from drivers.lidar.ouster_packet_layout import packet_layout
from drivers.lidar.pcap_udp import read_pcap_udp
from tests.list_can_bus import ListBus

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SHARED = Path("/work/shared/data")  # where the tests read the shared recordings, whatever the checkout
SHARED_OUSTER = SHARED / "ouster"


def mutate_bytes(data: bytes, rng: random.Random, specials: list[bytes] = ()) -> bytes:
    """Zero to four byte changes (a flip, a random byte, a special token written over), sometimes cut or grown."""
    b = bytearray(data)
    for _ in range(rng.randrange(5)):
        if not b:
            break
        at = rng.randrange(len(b))
        kind = rng.randrange(3)
        if kind == 0:
            b[at] ^= 1 << rng.randrange(8)
        elif kind == 1 or not specials:
            b[at] = rng.randrange(256)
        else:
            token = rng.choice(specials)
            b[at:at + len(token)] = token
    if rng.random() < 0.2:
        b = b[:rng.randrange(len(b) + 1)]
    elif rng.random() < 0.1:
        b += rng.randbytes(rng.randrange(1, 64))
    return bytes(b)


class OusterPacketCases:
    """A batch of 1-8 datagrams for one layout: a real capture's packets mutated, or random datagrams."""

    def __init__(self, rng: random.Random):
        self.rng = rng
        self.sources = []  # (layout, packets)
        for meta_path in sorted(SHARED_OUSTER.glob("OS-*.json")):
            pcaps = sorted(SHARED_OUSTER.glob(f"{meta_path.stem}*.pcap"))
            if not pcaps:
                continue
            layout = packet_layout(parse_metadata(meta_path.read_text()))
            packets = [d.payload for d in read_pcap_udp(pcaps[0], 7502).datagrams[:64]]
            if packets:
                self.sources.append((layout, packets))
        if not self.sources:
            raise SystemExit(f"ouster_packets: no Ouster capture with its metadata in {SHARED_OUSTER}")

    def __call__(self):
        layout, packets = self.rng.choice(self.sources)
        batch = []
        for _ in range(self.rng.randrange(1, 9)):
            if self.rng.random() < 0.15:
                size = self.rng.choice((0, 1, 16, layout.packet_size, self.rng.randrange(65508)))
                batch.append(self.rng.randbytes(size))
            else:
                batch.append(mutate_bytes(self.rng.choice(packets), self.rng))
        return layout, batch


def check_ouster_packets(case, counts: Counter) -> str:
    layout, datagrams = case
    batch = decode_packets(datagrams, layout)
    c = batch.counts
    if not (c.packets_in == len(datagrams) == c.packets_decoded + c.wrong_size + c.bad_header
            and batch.num_packets == c.packets_decoded):
        counts["counts_inconsistent"] += 1
    assembler = ouster_scan_assembler(layout)
    assembler.add(batch)
    assembler.flush()
    count_missing_packets(packet_sequence(batch, layout), layout)
    return "all decoded" if c.packets_decoded == len(datagrams) else "some refused"


GNSS_SPECIALS = [b"$", b"\xb5b", b"\xb5b\x01\x07\x5c\x00", b"\xb5b\x10\x02\xff\xff", b"\r\n", b"*", b"$GNGGA,",
                 b"\x00", b"\xff"]


class GnssCases:
    """A stretch of a real u-blox stream (NMEA + UBX), mutated, and where to cut it into reads."""

    def __init__(self, rng: random.Random):
        self.rng = rng
        paths = [SHARED / "gnss_gpsd/ublox-zed-f9p_hpg1.11.log", SHARED / "gnss_pyubx2/pygpsdata-SF-calibration.log",
                 SHARED / "gnss_pyubx2/pygpsdata-ESF.log", SHARED / "gnss_pyubx2/pygpsdata-HNR.log"]
        self.streams = [p.read_bytes()[:200_000] for p in paths if p.exists()] or [b"$GNGGA,0*00\r\n" * 100]

    def __call__(self):
        stream = self.rng.choice(self.streams)
        start = self.rng.randrange(len(stream))
        data = stream[start:start + self.rng.randrange(100, 4000)]
        for _ in range(self.rng.randrange(1, 6)):
            data = mutate_bytes(data, self.rng, GNSS_SPECIALS)
        cuts = sorted(self.rng.randrange(len(data) + 1) for _ in range(self.rng.randrange(6)))
        return data, cuts


def check_gnss(case, counts: Counter) -> str:
    data, cuts = case
    health = HealthCounters("gnss")
    framer, decoder = StreamFramer(health), GnssDecoder(health=health)
    published = []
    for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True):
        for frame in framer.feed(data[a:b]):
            published += decoder.decode(frame, 1)
    for frame in framer.flush():
        published += decoder.decode(frame, 1)
    published += decoder.flush()
    if framer.pending_bytes or framer.frame_bytes + framer.skipped_bytes != len(data):
        counts["bytes_unaccounted"] += 1
    for m in published:
        values = ([m.latitude_deg, m.longitude_deg, m.altitude_m, *m.position_covariance] if isinstance(m, GnssFix)
                  else [*m.velocity_enu_mps, *m.velocity_covariance] if isinstance(m, GnssVelocity)
                  else [*m.accel_mps2, *m.gyro_rps])
        if not all(math.isfinite(v) for v in values) or (isinstance(m, GnssFix) and (
                abs(m.latitude_deg) > 90 or abs(m.longitude_deg) > 180)):
            counts["bad_published"] += 1
            break
    return "published" if published else "nothing published"


class CanCases:
    """1-40 frames: the sim DBC's wheel speeds and yaw rate, real Ford Fusion frames, random ones; mutated."""

    def __init__(self, rng: random.Random):
        self.rng = rng
        self.config = load_config(CONFIGS / "sim.yaml").sensors.can.model_copy(update={"interface": "virtual"})
        self.dbc = CONFIGS / "sim_car.dbc"
        db = load_dbc(self.dbc)
        self.frames = []
        for i in range(50):
            self.frames += encode_wheel_speeds(db, self.config.signals, 10 + i * 0.3, 10.1, 9.9, 10 + i * 0.2,
                                               0.01 * i)
        for log in sorted((SHARED / "can_ford_fusion").glob("*.candump"))[:2]:
            with can.CanutilsLogReader(str(log)) as reader:
                for n, msg in enumerate(reader):
                    if n >= 2000:
                        break
                    self.frames.append(msg)

    def __call__(self):
        out = []
        for _ in range(self.rng.randrange(1, 41)):
            if self.rng.random() < 0.2:
                ext = self.rng.random() < 0.3
                data = self.rng.randbytes(self.rng.randrange(9))
                err, rtr = self.rng.random() < 0.1, self.rng.random() < 0.1
                out.append(can.Message(arbitration_id=self.rng.randrange(1 << (29 if ext else 11)),
                                       is_extended_id=ext, data=b"" if rtr else data, dlc=len(data),
                                       is_error_frame=err, is_remote_frame=rtr and not err, check=False,
                                       timestamp=1.0))
            else:
                base = self.rng.choice(self.frames)
                data = mutate_bytes(bytes(base.data), self.rng)[:64]
                out.append(can.Message(arbitration_id=base.arbitration_id, is_extended_id=base.is_extended_id,
                                       data=data, dlc=len(data), check=False, timestamp=base.timestamp,
                                       is_error_frame=self.rng.random() < 0.02))
        return out


def check_can(case, counts: Counter, config, dbc: Path) -> str:
    stop = threading.Event()
    published = []
    stats = run_can_driver(config, dbc, lambda t, m: published.append((t, m)), stop, HealthCounters("can"),
                           open_bus=lambda cfg, **kw: ListBus(case, stop), health_period_s=3600)
    if sum(t == CAN_FRAMES for t, _ in published) != len(case) or stats.frames != len(case):
        counts["frames_not_published"] += 1
    return "speeds decoded" if stats.wheel_speeds else "no speeds"


# --- the run ------------------------------------------------------------------------------------------------------
