"""The metadata records every log file carries: `roadlog` first (software version, resolved config, calibration,
host, start time), `roadlog.counts` at close (messages and last seq per topic)."""

SOFTWARE_VERSION = "roadlog 0.1.0"
METADATA_NAME = "roadlog"
COUNTS_METADATA_NAME = "roadlog.counts"
# key of the `roadlog` record: "[lat, lon, alt]" of the ENU frame a log's `pose` topic is given in (an importer's);
# without it the poses are in a local frame that is not geo-referenced
POSE_ENU_ORIGIN_KEY = "pose_enu_origin"
