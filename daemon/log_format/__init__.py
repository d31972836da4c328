"""The log format: MCAP files, one channel per topic, protobuf schemas Foxglove can open (docs/log-format.md).

One module per concern: `writer` (LogWriter), `reader` (read_log, read_metadata), `record_scan` (CRC-checked chunks,
a trusted summary, the walk past damage), `recovery` (recover_log),
`foxglove_schemas` (messages to and from Foxglove's well-known protobufs), `metadata_records` (the names of the
metadata records every file carries, the clock of the log times), `static_transforms` (vehicle -> each sensor),
`mask_palette` (masks in colour), `proto_files` (the `.proto` files shipped in `proto/`).
"""
