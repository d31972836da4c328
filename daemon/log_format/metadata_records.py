"""The metadata records every log file carries: `roadlog` first (software version, resolved config, calibration,
host, start time), `roadlog.counts` at close (messages and last seq per topic)."""

SOFTWARE_VERSION = "roadlog 0.1.0"
METADATA_NAME = "roadlog"
COUNTS_METADATA_NAME = "roadlog.counts"
