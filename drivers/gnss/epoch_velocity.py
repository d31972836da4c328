"""The velocity of each receiver epoch, as a GnssVelocity: UBX's when the receiver sends one, else NMEA's.

UBX NAV-PVT and NAV-PVAT give velN/velE/velD (the antenna's Doppler velocity, with sAcc as each axis's 1-sigma). For a
receiver that sends no UBX velocity, NMEA RMC or VTG give speed and course over ground: horizontal only, the vertical
given NMEA_VERTICAL_SIGMA_MPS; no accuracy in NMEA, so NMEA_VELOCITY_SIGMA_MPS. Stamped as the epoch's fix, once an
epoch: the first NMEA one is held until a message of another epoch comes, since a u-blox receiver sends its RMC before
the NAV-PVT of the same epoch, which replaces it; once an epoch has passed without a UBX velocity, NMEA ones go out at
once. RMC carries its epoch's time; VTG carries none and is taken for the epoch whose timed sentences (GGA, RMC, GST,
ZDA) come both before and after it, else counted (`nmea_vtg_epoch_ambiguous`) and skipped.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

import pynmea2

from daemon.spine.messages import GnssVelocity
from drivers.gnss.receiver_epochs import (
    RECENT_EPOCHS,
    UNKNOWN_COVARIANCE,
    covariance_diagonal,
    covariance_of_variances,
    epoch_key,
)

MAX_VELOCITY_MPS = 500.0  # a car's receiver reporting more is garbled (u-blox's own dynamic limit is 500 m/s)
KNOT_MPS = 1852.0 / 3600.0
# NMEA gives no velocity accuracy: a stated, conservative 1-sigma per horizontal axis. Above what real receivers show:
# the static u-blox NMEA captures of /work/shared/data/gnss_gpsd report speeds of 0.03-0.09 m/s RMS (max 0.3 m/s);
# the ZED-F9R drive's own sAcc is 0.08 m/s median, 0.19 m/s at the 95th percentile; a moving boat's RMC velocities
# (bundg_zeus_9.log) differ from its fixes' central differences by 0.23-0.25 m/s RMS per axis. NMEA also cannot say
# when an epoch is bad (few satellites, multipath) or how much the receiver filters its course and speed.
NMEA_VELOCITY_SIGMA_MPS = 0.25
# NMEA has no vertical velocity: 0 m/s with this 1-sigma, which makes the pose fusion's update take nothing from it
# (its gain on the vertical velocity is below 1e-6) while the horizontal axes are used.
NMEA_VERTICAL_SIGMA_MPS = 1000.0
NMEA_NOT_VALID_MODES = ("N",)  # NMEA 2.3 mode indicator (RMC, VTG): data not valid


@dataclass(slots=True)
class _PendingVtg:
    """A VTG (no time of its own) waiting for the next timed sentence."""

    time_of_day_before_ns: int | None  # of the timed sentence before it
    knots: object  # as pynmea2 gives them (checked when used)
    course_deg: object
    host_mono_ns: int


class EpochVelocity:
    """Stateful, owned by a GnssDecoder: keeps the held NMEA velocity, the VTG waiting for its epoch and the epochs
    already given a velocity. Counts into the decoder's `counts`; rejects and drops through the decoder's callables;
    `nmea_utc_ns` maps an NMEA time of day to UTC ns with the decoder's date (None while it has none)."""

    def __init__(self, counts: Counter[str], reject: Callable[[str, BaseException], None],
                 drop: Callable[[str], None], nmea_utc_ns: Callable[[int], int | None]) -> None:
        self._counts = counts
        self._reject = reject
        self._drop = drop
        self._nmea_utc_ns = nmea_utc_ns
        self._recent_velocity_ms: deque[int] = deque(maxlen=RECENT_EPOCHS)
        self._ubx_velocity_seen = False  # then NMEA velocities are not used: UBX gives the vertical and sAcc
        self._held_nmea_velocity: GnssVelocity | None = None  # until a message of another epoch (or a UBX one) comes
        self._nmea_velocity_at_once = False  # an epoch passed without a UBX velocity: NMEA ones go out at once
        self._last_nmea_time_of_day_ns: int | None = None  # of the last timed NMEA sentence (GGA, RMC, GST, ZDA)
        self._pending_vtg: _PendingVtg | None = None  # a VTG waiting for the next timed sentence
        self._invalid_time_of_day_ns: int | None = None  # an epoch without a fix (RMC status V, GGA quality 0)

    def flush(self) -> list[GnssVelocity]:
        """The stream has ended: the held NMEA velocity goes out; a waiting VTG's epoch is unknown (counted)."""
        out = self._release(None)
        if self._pending_vtg is not None:
            self._counts["nmea_vtg_epoch_ambiguous"] += 1  # no sentence after it: its epoch is unknown
        self._pending_vtg = None
        self._last_nmea_time_of_day_ns = None
        return out

    # ---- UBX ----------------------------------------------------------------------------------------
    def on_ubx(self, msg, sensor_time: int, host_mono_ns: int) -> list[GnssVelocity]:
        """The epoch's velocity (NAV-PVT, NAV-PVAT: mm/s, north/east/down) in east/north/up m/s, once an epoch; a
        garbled one (not finite, over MAX_VELOCITY_MPS) is rejected and counted."""
        self._ubx_velocity_seen = True
        out = self._release(sensor_time)  # one of an earlier epoch goes out
        if self._held_nmea_velocity is not None:  # this epoch's: the receiver's own velocity replaces it
            self._held_nmea_velocity = None
            self._counts["ignored_nmea_velocity_ubx_gives_it"] += 1
        if epoch_key(sensor_time) in self._recent_velocity_ms:
            self._counts["duplicate_velocity_epoch"] += 1
            return out
        velocity = (msg.velE / 1000.0, msg.velN / 1000.0, -msg.velD / 1000.0)
        s_acc = msg.sAcc / 1000.0
        if not (all(math.isfinite(v) and abs(v) <= MAX_VELOCITY_MPS for v in velocity) and math.isfinite(s_acc)
                and s_acc >= 0):  # the epoch's fix stands; only its velocity is lost
            self._reject("ubx_bad_velocity", ValueError(f"velocity {velocity} m/s, sAcc {s_acc} m/s"))
            return out
        self._first_velocity_of_epoch(sensor_time)
        self._counts["velocity"] += 1
        known = s_acc > 0
        covariance = covariance_diagonal(s_acc, s_acc, s_acc) if known else UNKNOWN_COVARIANCE
        return out + [GnssVelocity(sensor_time_ns=sensor_time, host_mono_ns=host_mono_ns, velocity_enu_mps=velocity,
                                   velocity_covariance=covariance, covariance_type=2 if known else 0)]

    # ---- NMEA ---------------------------------------------------------------------------------------
    def on_timed_sentence(self, time_of_day_ns: int, no_fix: bool) -> list[GnssVelocity]:
        """A timed NMEA sentence (GGA, RMC, GST, ZDA) came: a waiting VTG's velocity, and the held one if this
        sentence is of another epoch. `no_fix` (RMC status V, GGA quality 0) marks its epoch invalid."""
        if no_fix:
            self._invalid_time_of_day_ns = time_of_day_ns
        out = self._close_vtg(time_of_day_ns)
        sensor_time = self._nmea_utc_ns(time_of_day_ns)
        if sensor_time is not None:
            out += self._release(sensor_time)
        return out

    def on_rmc(self, rmc: pynmea2.TalkerSentence, time_of_day_ns: int, no_fix: bool,
               host_mono_ns: int) -> list[GnssVelocity]:
        """The RMC's velocity (after on_timed_sentence and the decoder's date of the same RMC)."""
        if no_fix:
            self._counts["nmea_velocity_invalid"] += 1
            return []
        return self._nmea_velocity(time_of_day_ns, rmc.spd_over_grnd, rmc.true_course, host_mono_ns)

    def on_vtg(self, vtg: pynmea2.TalkerSentence, host_mono_ns: int) -> None:
        """Hold the VTG until the next timed sentence says whether it lies inside one epoch."""
        if self._pending_vtg is not None:
            self._counts["nmea_vtg_epoch_ambiguous"] += 1  # two VTGs with no timed sentence between them
        self._pending_vtg = None
        if vtg.faa_mode in NMEA_NOT_VALID_MODES:
            self._counts["nmea_velocity_invalid"] += 1
            return
        knots = vtg.spd_over_grnd_kts
        if knots is None and vtg.spd_over_grnd_kmph is not None:
            knots = float(vtg.spd_over_grnd_kmph) / 1.852
        self._pending_vtg = _PendingVtg(self._last_nmea_time_of_day_ns, knots, vtg.true_track, host_mono_ns)

    def _close_vtg(self, time_of_day_ns: int) -> list[GnssVelocity]:
        """A timed sentence came: the waiting VTG's velocity if the sentence before it had the same time."""
        pending, self._pending_vtg = self._pending_vtg, None
        self._last_nmea_time_of_day_ns = time_of_day_ns
        if pending is None:
            return []
        if pending.time_of_day_before_ns != time_of_day_ns:
            self._counts["nmea_vtg_epoch_ambiguous"] += 1  # at an epoch boundary: either epoch's
            return []
        if time_of_day_ns == self._invalid_time_of_day_ns:
            self._counts["nmea_velocity_invalid"] += 1
            return []
        return self._nmea_velocity(time_of_day_ns, pending.knots, pending.course_deg, pending.host_mono_ns)

    def _nmea_velocity(self, time_of_day_ns: int, knots, course_deg, host_mono_ns: int) -> list[GnssVelocity]:
        """Speed (knots) and true course over ground as an east/north velocity; an empty speed is counted, a garbled
        one rejected (the fix stands). Without a course (receivers leave it empty when nearly still) the velocity is 0
        with the speed added to the variance, as a speed of unknown direction."""
        if self._ubx_velocity_seen:
            self._counts["ignored_nmea_velocity_ubx_gives_it"] += 1
            return []
        if knots is None:
            self._counts["nmea_velocity_empty"] += 1
            return []
        try:
            speed = float(knots) * KNOT_MPS
            course = None if course_deg is None else float(course_deg)
            if not (math.isfinite(speed) and 0.0 <= speed <= MAX_VELOCITY_MPS):
                raise ValueError(f"speed {speed} m/s")
            if course is not None and not (math.isfinite(course) and 0.0 <= course <= 360.0):
                raise ValueError(f"course {course} deg")
        except (ValueError, TypeError, ArithmeticError) as exc:
            self._reject("nmea_bad_velocity", exc)
            return []
        sensor_time = self._nmea_utc_ns(time_of_day_ns)
        if sensor_time is None:
            self._drop("no_date")
            return []
        sigma2 = NMEA_VELOCITY_SIGMA_MPS**2
        if course is None:
            self._counts["nmea_velocity_without_course"] += 1
            east = north = 0.0
            sigma2 += speed**2 / 2.0  # each axis of a speed in a uniformly unknown direction
        else:
            east, north = speed * math.sin(math.radians(course)), speed * math.cos(math.radians(course))
        velocity = GnssVelocity(sensor_time_ns=sensor_time, host_mono_ns=host_mono_ns,
                                velocity_enu_mps=(east, north, 0.0),
                                velocity_covariance=covariance_of_variances(sigma2, sigma2,
                                                                            NMEA_VERTICAL_SIGMA_MPS**2),
                                covariance_type=1)
        out = self._release(sensor_time)
        if self._held_nmea_velocity is not None or epoch_key(sensor_time) in self._recent_velocity_ms:
            self._counts["duplicate_velocity_epoch"] += 1  # e.g. the VTG after its epoch's RMC
            return out
        if not self._nmea_velocity_at_once:
            self._held_nmea_velocity = velocity
            return out
        self._first_velocity_of_epoch(sensor_time)
        self._counts["velocity"] += 1
        return out + [velocity]

    # ---- once an epoch ------------------------------------------------------------------------------
    def _release(self, sensor_time_ns: int | None) -> list[GnssVelocity]:
        """The held NMEA velocity, once a message of another epoch than its own comes (None: the stream ended); from
        then on, until a UBX velocity comes, NMEA velocities go out at once (the receiver sends none of its own)."""
        held = self._held_nmea_velocity
        if held is None or held.sensor_time_ns == sensor_time_ns:
            return []
        self._held_nmea_velocity = None
        self._nmea_velocity_at_once = sensor_time_ns is not None
        if not self._first_velocity_of_epoch(held.sensor_time_ns):
            return []
        self._counts["velocity"] += 1
        return [held]

    def _first_velocity_of_epoch(self, sensor_time_ns: int) -> bool:
        """True once per epoch (remembered); a second velocity of an epoch is counted."""
        epoch_ms = epoch_key(sensor_time_ns)
        if epoch_ms in self._recent_velocity_ms:
            self._counts["duplicate_velocity_epoch"] += 1
            return False
        self._recent_velocity_ms.append(epoch_ms)
        return True
