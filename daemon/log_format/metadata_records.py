"""The metadata records every log file carries: `roadlog` first (software version, resolved config, calibration,
host, start time, the clock of the log times), a `roadlog.channel` per channel as it is opened (so the chunks after
a damaged one still decode: the channel's own record sits in the chunk where it was first used), `roadlog.counts` at
close (messages and last seq per topic)."""

from __future__ import annotations

import importlib.metadata
import json
import zlib
from collections.abc import Mapping

from mcap.records import Channel, Schema

try:  # the installed distribution's (pyproject.toml), the one place the version is written
    SOFTWARE_VERSION = f"roadlog {importlib.metadata.version('roadlog')}"
except importlib.metadata.PackageNotFoundError:  # run from a checkout that was never installed
    SOFTWARE_VERSION = "roadlog (not installed)"
METADATA_NAME = "roadlog"
COUNTS_METADATA_NAME = "roadlog.counts"
CHANNEL_METADATA_NAME = "roadlog.channel"
# key of the `roadlog` record: "[lat, lon, alt]" of the ENU frame a log's `pose` topic is given in (an importer's);
# without it the poses are in a local frame that is not geo-referenced
POSE_ENU_ORIGIN_KEY = "pose_enu_origin"
# keys of the `roadlog` record naming the clock of the MCAP log times: "utc" = UTC ns, log_time = host_mono_ns +
# log_time_offset_ns (one offset per file, so a file's log-time order is its host-time order). A log written before
# them has neither: its log times are the host's monotonic clock (offset 0).
LOG_TIME_CLOCK_KEY = "log_time_clock"
LOG_TIME_UTC = "utc"
LOG_TIME_OFFSET_KEY = "log_time_offset_ns"
# the same offset in each channel's metadata, so every message maps back to its host time on its own (also in a
# scanned file whose `roadlog` record was torn off)
CHANNEL_OFFSET_KEY = "roadlog.log_time_offset_ns"
_CHANNEL_KEYS = ("channel_id", "topic", "message_encoding", "schema_id", "schema_name", "schema_encoding", "metadata")


def _crc(fields: dict[str, str]) -> str:
    return str(zlib.crc32(json.dumps([fields[k] for k in _CHANNEL_KEYS]).encode()))


def channel_record(channel: Channel, schema: Schema) -> dict[str, str]:
    """The `roadlog.channel` record of one channel and its schema (the schema's name, not its bytes), with a CRC."""
    fields = {"channel_id": str(channel.id), "topic": channel.topic, "message_encoding": channel.message_encoding,
              "schema_id": str(schema.id), "schema_name": schema.name, "schema_encoding": schema.encoding,
              "metadata": json.dumps(channel.metadata, sort_keys=True)}
    return {**fields, "crc32": _crc(fields)}


def channel_from_record(fields: dict[str, str]) -> tuple[Channel, Schema] | None:
    """The channel and schema (without its bytes) a `roadlog.channel` record describes; None when it fails its CRC."""
    try:
        if fields.get("crc32") != _crc(fields):
            return None
        schema = Schema(id=int(fields["schema_id"]), name=fields["schema_name"], encoding=fields["schema_encoding"],
                        data=b"")
        metadata = json.loads(fields["metadata"])
        channel = Channel(id=int(fields["channel_id"]), topic=fields["topic"], schema_id=schema.id,
                          message_encoding=fields["message_encoding"],
                          metadata={str(k): str(v) for k, v in metadata.items()})
    except (KeyError, ValueError, TypeError, AttributeError):
        return None
    return channel, schema


def log_time_offset(metadata: Mapping[str, str]) -> int:
    """How far a channel's (CHANNEL_OFFSET_KEY) or a file's (`roadlog` record) log times lie after its messages' host
    monotonic times: the offset it names, 0 for a log written on the monotonic clock (before UTC log times) or by
    another tool."""
    value = metadata.get(CHANNEL_OFFSET_KEY)
    if value is None and metadata.get(LOG_TIME_CLOCK_KEY) == LOG_TIME_UTC:
        value = metadata.get(LOG_TIME_OFFSET_KEY)
    try:
        return int(value) if value is not None else 0
    except ValueError:
        return 0
