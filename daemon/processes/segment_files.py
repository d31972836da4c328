"""The recorder's segment files in its folder: their names (which sort by time), which are closed or quarantined,
the recovery of the unclosed ones a crash or power cut left behind, and where a restarted recorder resumes: the
highest seq per topic that its daemon run's segments hold.

    roadlog_<UTC start>_<index>.mcap            a closed segment: the UTC of its first message where the time
                                                anchors give it (closed_name), else as it was opened
    roadlog_<UTC start>_<index>.mcap.open       the segment being written (or left by a crash), this host's UTC
    roadlog_<UTC start>_<index>.mcap.recovering an unclosed segment being recovered into its `.mcap`
    roadlog_<UTC start>_<index>.mcap.damaged    an unclosed segment that could not be read in full, kept as it was
"""

from __future__ import annotations

import json
import logging
import os
from datetime import UTC, datetime
from pathlib import Path

from daemon.bus.ring_layout import process_start_ticks
from daemon.log_format.metadata_records import COUNTS_METADATA_NAME, METADATA_NAME
from daemon.log_format.reader import read_metadata
from daemon.log_format.record_scan import trusted_summary
from daemon.log_format.recovery import recover_log
from daemon.processes import disk_policy
from daemon.spine.config import CarConfig, ConfigError, data_dir

SEGMENT_PREFIX = "roadlog_"
SEGMENT_SUFFIX = ".mcap"
OPEN_SUFFIX = ".open"
RECOVERING_SUFFIX = ".recovering"
DAMAGED_SUFFIX = ".damaged"
log = logging.getLogger(__name__)


def segment_name(utc_ns: int, index: int) -> str:
    """`roadlog_20261123T101500Z_0003.mcap`: names sort by start time, then by index."""
    stamp = datetime.fromtimestamp(utc_ns / 1e9, UTC).strftime("%Y%m%dT%H%M%SZ")
    return f"{SEGMENT_PREFIX}{stamp}_{index:04d}{SEGMENT_SUFFIX}"


def anchored_utc_ns(anchor: tuple[int, int] | None, host_mono_ns: int | None) -> int | None:
    """The UTC of a host time on the log's clock through a time anchor (host_mono_ns, utc_ns); None without both."""
    return None if anchor is None or host_mono_ns is None else anchor[1] + host_mono_ns - anchor[0]


def closed_name(open_name: str, first_utc_ns: int | None) -> str:
    """The name a segment opened as `open_name` is closed under: named by the UTC of its first message where known,
    else as it was opened (by this host's clock then); its index kept."""
    name = open_name[: -len(OPEN_SUFFIX)]
    index = _segment_index(name)
    return name if first_utc_ns is None or index is None else segment_name(first_utc_ns, index)


def _segment_index(name: str) -> int | None:
    stem = name.split(SEGMENT_SUFFIX)[0]
    tail = stem.rsplit("_", 1)[-1]
    return int(tail) if name.startswith(SEGMENT_PREFIX) and tail.isdigit() else None


def _segments(output_dir: Path, pattern: str) -> list[disk_policy.Segment]:
    """The files matching `pattern` in `output_dir` with their sizes, oldest first: by index, which a clock set back
    cannot reorder; a file gone meanwhile is left out."""
    out = []
    for p in sorted(output_dir.glob(pattern), key=lambda p: (_segment_index(p.name) or 0, p.name)):
        try:
            out.append(disk_policy.Segment(p, p.stat().st_size))
        except FileNotFoundError:
            continue
    return out


def closed_segments(output_dir: Path) -> list[disk_policy.Segment]:
    """The closed segments in `output_dir`, oldest first."""
    return _segments(output_dir, f"{SEGMENT_PREFIX}*{SEGMENT_SUFFIX}")


def quarantined_segments(output_dir: Path) -> list[disk_policy.Segment]:
    """The quarantined segments (`NAME.mcap.damaged`, see recover_unclosed) in `output_dir`, oldest first."""
    return _segments(output_dir, f"{SEGMENT_PREFIX}*{SEGMENT_SUFFIX}{DAMAGED_SUFFIX}*")


def oldest_first(output_dir: Path) -> list[disk_policy.Segment]:
    """The closed and the quarantined segments together, oldest first: what the disk policy may delete."""
    return sorted(closed_segments(output_dir) + quarantined_segments(output_dir),
                  key=lambda seg: (_segment_index(seg.path.name) or 0, seg.path.name))


def drive_seconds(path: Path) -> float:
    """The seconds of drive a segment holds, its first to its last message (from its trusted summary); 0 for one
    without (a quarantined segment)."""
    try:
        with open(path, "rb") as f:
            summary, _ = trusted_summary(f, os.fstat(f.fileno()).st_size)
    except OSError:
        return 0.0
    stats = summary.statistics if summary is not None else None
    if stats is None or not stats.message_count:
        return 0.0
    start = stats.message_start_time
    if start == 0:  # the camera calibrations are logged at time 0: the drive began when the segment was opened
        opened = read_metadata(path).get(METADATA_NAME, {}).get("start_mono_ns", "")
        start = int(opened) if opened.isdigit() else stats.message_end_time
    return max(0, stats.message_end_time - start) / 1e9


def next_segment_index(output_dir: Path) -> int:
    """One past the highest index of any segment (open, closed or being recovered) in the folder."""
    indices = [_segment_index(p.name) for p in output_dir.glob(f"{SEGMENT_PREFIX}*")]
    return 1 + max((i for i in indices if i is not None), default=-1)


def recover_unclosed(output_dir: Path, config: CarConfig) -> list[dict]:
    """Turn every `.mcap.open` left by a crash into a readable `.mcap` holding each of its intact chunks; one report
    per file. A source with bytes that could not be read (a torn or damaged stretch, a cut-off end) is kept whole
    as `NAME.mcap.damaged` (quarantined: never deleted, never read again by the recorder); a source read in full
    is removed. Whatever the file holds, the recorder goes on: only a destination it cannot write (a full disk)
    leaves the `.open` file for a later start."""
    reports = []
    for src in sorted(output_dir.glob(f"{SEGMENT_PREFIX}*{SEGMENT_SUFFIX}{OPEN_SUFFIX}")):
        dst = src.with_name(src.name[: -len(OPEN_SUFFIX)])
        tmp = dst.with_name(dst.name + RECOVERING_SUFFIX)
        report: dict = {"from": str(src), "to": None, "quarantined": None}
        try:
            fr = recover_log(src, tmp, config)
            os.replace(tmp, dst)
            report.update(to=str(dst), messages=fr.messages, bytes_skipped=fr.bytes_skipped,
                          damaged_chunks=fr.damaged_chunks, error=fr.error)
        except OSError as exc:  # the recovered file cannot be written: keep the original, a later start may manage
            tmp.unlink(missing_ok=True)
            log.error("cannot recover %s: %s", src, exc)
            reports.append({**report, "error": f"{type(exc).__name__}: {exc}"})
            continue
        except Exception as exc:  # noqa: BLE001 - nothing in one segment may stop the recording: quarantine it
            tmp.unlink(missing_ok=True)
            fr = None
            report.update(error=f"{type(exc).__name__}: {exc}")
        if fr is None or fr.bytes_skipped or fr.damaged_chunks:
            try:
                kept = quarantine(src, dst)
            except OSError as exc:  # it stays `.open`: the next start recovers it again
                log.error("cannot quarantine %s: %s", src, exc)
                reports.append({**report, "error": f"{report['error']}; not quarantined: {exc}"})
                continue
            report["quarantined"] = str(kept)
            unread = f"{fr.bytes_skipped} of its {fr.bytes_total} bytes" if fr else "it"
            recovered = f"{fr.messages} messages recovered into {dst.name}" if fr else "nothing recovered"
            log.error("quarantined %s as %s: %s could not be read (%s); %s", src.name, kept.name, unread,
                      report["error"], recovered)
        else:
            src.unlink()
            log.warning("recovered unclosed segment %s -> %s: %d messages (%s)", src.name, dst.name, fr.messages,
                        fr.error or "no footer")
        reports.append(report)
    return reports


def quarantine(src: Path, dst: Path) -> Path:
    """Rename an unclosed segment that could not be read in full to `NAME.mcap.damaged` (a number added when one is
    there already); its path."""
    target = dst.with_name(dst.name + DAMAGED_SUFFIX)
    n = 1
    while target.exists():
        target = dst.with_name(f"{dst.name}{DAMAGED_SUFFIX}.{n}")
        n += 1
    os.replace(src, target)
    return target


def check_output_dir(config: CarConfig, config_path: str | Path, override: str | Path | None = None) -> Path:
    """The recorder's folder (recorder.output_dir, or the override), once it is sure it can be made and written
    (the recorder's start-up check, also run by `roadlog check-config`): ConfigError otherwise. A relative one is
    taken from the working directory, never from the config's folder (`data_dir`); `config_path` is the check's
    common signature."""
    del config_path
    folder = data_dir(config, override)
    existing = folder
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"recorder.output_dir {str(folder)!r}: {str(existing)!r} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"recorder.output_dir {str(folder)!r}: {str(existing)!r} is not writable by this user")
    return folder


def daemon_run() -> str:
    """Which daemon run this process belongs to: its parent (the supervisor) by pid and start time."""
    parent = os.getppid()
    return f"{parent}:{process_start_ticks(parent) or 0}"


def last_recorded_seqs(output_dir: Path, run: str) -> dict[str, int]:
    """Per topic, the highest seq in the closed segments (recovered ones included) that recorders of daemon
    run `run` wrote: the newest segments, back to the first from another run."""
    out: dict[str, int] = {}
    for segment in reversed(closed_segments(output_dir)):
        meta = read_metadata(segment.path)
        if meta.get(METADATA_NAME, {}).get("daemon_run") != run:
            break
        for topic, seq in json.loads(meta.get(COUNTS_METADATA_NAME, {}).get("last_seq_per_topic", "{}")).items():
            out[topic] = max(out.get(topic, -1), seq)
    return out
