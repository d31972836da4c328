"""The car's wheel-speed and yaw-rate CAN signals (named in the config, laid out by the DBC) <-> WheelSpeeds.

Decoding turns one received wheel-speed frame into one `WheelSpeeds` (m/s, rad/s) carrying the yaw rate of
the latest yaw frame. Encoding (the simulator's side) does the reverse. A configured message that has a
signal named COUNTER is checked for gaps; one with a signal named CHECKSUM is checked with the Toyota
checksum, stored in the frame's last byte (see `toyota_checksum`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import can
import cantools
from cantools.database import Database, Message

from daemon.spine.config import CanSignals
from daemon.spine.messages import WheelSpeeds

SPEED_TO_MPS = {"m/s": 1.0, "km/h": 1.0 / 3.6}  # "rad/s" (a wheel's angular rate) scales by its radius instead
YAW_TO_RPS = {"rad/s": 1.0, "deg/s": math.pi / 180.0}
YAW_STALE_NS = 1_000_000_000  # a yaw rate older than this (frame time) is not paired with wheel speeds
COUNTER_SIGNAL = "COUNTER"
CHECKSUM_SIGNAL = "CHECKSUM"


class WheelSpeedLayoutError(ValueError):
    """The configured signal names do not match the DBC."""


class CanDecodeError(ValueError):
    """A frame of a configured message that cannot be decoded (short, bad checksum, ...)."""


@dataclass(frozen=True)
class WheelSpeedLayout:
    """Where the four wheel speeds and the yaw rate live in the DBC, and their scales to SI units."""

    wheel_message: Message
    wheel_signals: tuple[str, str, str, str]  # front-left, front-right, rear-left, rear-right
    yaw_message: Message | None
    yaw_signal: str | None
    speed_to_mps: float
    yaw_to_rps: float


def load_dbc(path: str | Path) -> Database:
    return cantools.database.load_file(str(path), strict=False)


def _find(db: Database, dotted: str) -> tuple[Message, str]:
    message_name, signal_name = dotted.split(".")
    try:
        message = db.get_message_by_name(message_name)
    except KeyError:
        raise WheelSpeedLayoutError(f"DBC has no message {message_name!r} (signal {dotted})") from None
    if signal_name not in {s.name for s in message.signals}:
        raise WheelSpeedLayoutError(f"DBC message {message_name} has no signal {signal_name!r}")
    return message, signal_name


def wheel_speed_layout(db: Database, signals: CanSignals) -> WheelSpeedLayout:
    """Resolve the configured MESSAGE.SIGNAL names; the four wheel speeds must share one message."""
    wheels = [_find(db, name) for name in
              (signals.wheel_speed_fl, signals.wheel_speed_fr, signals.wheel_speed_rl, signals.wheel_speed_rr)]
    messages = {m.name for m, _ in wheels}
    if len(messages) != 1:
        raise WheelSpeedLayoutError(f"the four wheel speeds must be in one message, got {sorted(messages)}")
    yaw_message, yaw_signal = _find(db, signals.yaw_rate) if signals.yaw_rate else (None, None)
    if yaw_message is not None and yaw_message.frame_id == wheels[0][0].frame_id:
        raise WheelSpeedLayoutError("the yaw rate must be in a message of its own, not the wheel-speed message")
    return WheelSpeedLayout(
        wheel_message=wheels[0][0],
        wheel_signals=(wheels[0][1], wheels[1][1], wheels[2][1], wheels[3][1]),
        yaw_message=yaw_message,
        yaw_signal=yaw_signal,
        speed_to_mps=speed_to_mps(signals),
        yaw_to_rps=YAW_TO_RPS[signals.yaw_rate_unit],
    )


def speed_to_mps(signals: CanSignals) -> float:
    """The factor from the DBC's wheel-speed unit to m/s: an angular rate (rad/s) times the wheel's radius."""
    return signals.wheel_radius_m if signals.speed_unit == "rad/s" else SPEED_TO_MPS[signals.speed_unit]


def toyota_checksum(frame_id: int, data: bytes) -> int:
    """(id low byte + id high byte + length + sum of all bytes but the last) & 0xFF."""
    return (frame_id & 0xFF) + ((frame_id >> 8) & 0xFF) + len(data) + sum(data[:-1]) & 0xFF


def _signal_names(message: Message) -> set[str]:
    return {s.name for s in message.signals}


@dataclass
class WheelSpeedDecoder:
    """Decodes received frames; keeps the latest yaw rate and each message's last rolling counter."""

    layout: WheelSpeedLayout
    yaw_rate_rps: float = math.nan
    yaw_time_ns: int = 0
    counter_gaps: int = 0
    _last_counter: dict[int, int] = field(default_factory=dict)

    def _message_for(self, arbitration_id: int, is_extended_id: bool) -> Message | None:
        for message in (self.layout.wheel_message, self.layout.yaw_message):
            if message is not None and message.frame_id == arbitration_id \
                    and message.is_extended_frame == is_extended_id:
                return message
        return None

    def _decode(self, message: Message, data: bytes) -> dict:
        if len(data) < message.length:
            raise CanDecodeError(f"{message.name}: {len(data)} bytes, DBC says {message.length}")
        data = bytes(data[: message.length])
        names = _signal_names(message)
        if CHECKSUM_SIGNAL in names and data[-1] != toyota_checksum(message.frame_id, data):
            raise CanDecodeError(f"{message.name}: checksum 0x{data[-1]:02x}, "
                                 f"expected 0x{toyota_checksum(message.frame_id, data):02x}")
        try:
            values = message.decode(data, decode_choices=False, scaling=True)
        except (cantools.database.DecodeError, ValueError) as exc:
            raise CanDecodeError(f"{message.name}: {exc}") from None
        if COUNTER_SIGNAL in names:
            counter = int(values[COUNTER_SIGNAL])
            modulus = 1 << message.get_signal_by_name(COUNTER_SIGNAL).length
            last = self._last_counter.get(message.frame_id)
            if last is not None and counter != (last + 1) % modulus:
                self.counter_gaps += 1
            self._last_counter[message.frame_id] = counter
        return values

    def decode(self, arbitration_id: int, is_extended_id: bool, data: bytes, time_ns: int) -> WheelSpeeds | None:
        """A WheelSpeeds for a wheel-speed frame, None for any other frame; raises CanDecodeError."""
        message = self._message_for(arbitration_id, is_extended_id)
        if message is None:
            return None
        values = self._decode(message, data)
        layout = self.layout
        if message is layout.yaw_message:
            self.yaw_rate_rps = float(values[layout.yaw_signal]) * layout.yaw_to_rps
            self.yaw_time_ns = time_ns
            return None
        fl, fr, rl, rr = (float(values[name]) * layout.speed_to_mps for name in layout.wheel_signals)
        fresh = self.yaw_time_ns and abs(time_ns - self.yaw_time_ns) <= YAW_STALE_NS
        return WheelSpeeds(
            sensor_time_ns=time_ns,
            front_left_mps=fl,
            front_right_mps=fr,
            rear_left_mps=rl,
            rear_right_mps=rr,
            yaw_rate_rps=self.yaw_rate_rps if fresh else math.nan,
        )


def _encode(message: Message, values: dict[str, float], counter: int) -> can.Message:
    names = _signal_names(message)
    full = {s.name: 0 for s in message.signals}
    full.update(values)
    if COUNTER_SIGNAL in names:
        full[COUNTER_SIGNAL] = counter % (1 << message.get_signal_by_name(COUNTER_SIGNAL).length)
    data = bytearray(message.encode(full, scaling=True, padding=False, strict=True))
    if CHECKSUM_SIGNAL in names:
        data[-1] = toyota_checksum(message.frame_id, bytes(data))
    return can.Message(arbitration_id=message.frame_id, is_extended_id=message.is_extended_frame, data=data)


def encode_wheel_speeds(db: Database, signals: CanSignals, fl: float, fr: float, rl: float, rr: float,
                        yaw_rate_rps: float, counter: int = 0) -> list[can.Message]:
    """The frames a car would send for these wheel speeds (m/s) and yaw rate (rad/s): yaw frame first.

    Values outside a signal's DBC range raise cantools' EncodeError; the yaw frame is left out when the
    config names no yaw signal.
    """
    layout = wheel_speed_layout(db, signals)
    frames = []
    if layout.yaw_message is not None:
        frames.append(_encode(layout.yaw_message, {layout.yaw_signal: yaw_rate_rps / layout.yaw_to_rps}, counter))
    speeds = dict(zip(layout.wheel_signals, (fl, fr, rl, rr), strict=True))
    frames.append(_encode(layout.wheel_message, {k: v / layout.speed_to_mps for k, v in speeds.items()}, counter))
    return frames
