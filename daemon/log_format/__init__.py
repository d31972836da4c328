"""The log format: MCAP files, one channel per topic, protobuf schemas Foxglove can open (docs/log-format.md).

One module per concern: `writer` (LogWriter), `reader` (read_log, read_metadata), `recovery` (recover_log),
`foxglove_schemas` (messages to and from Foxglove's well-known protobufs), `metadata_records` (the names of the
metadata records every file carries).
"""
