"""The metadata records every log file carries: `roadlog` first (software version, resolved config, calibration,
host, start time), a `roadlog.channel` per channel as it is opened (so the chunks after a damaged one still decode:
the channel's own record sits in the chunk where it was first used), `roadlog.counts` at close (messages and last
seq per topic)."""

from __future__ import annotations

import importlib.metadata
import json
import zlib

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
