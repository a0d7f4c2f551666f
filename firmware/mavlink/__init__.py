"""MAVLink for the vehicle, in two halves.

The flight process imports only `bridge` and `ipc` (no pymavlink): the vehicle, its
failsafe and the estimator stay in the 1 kHz loop. Everything that parses or encodes
MAVLink runs in a separate process, started by `bridge.start_mavlink`, so it never competes
with the loop for the GIL: `process` (the Station: links and I/O), `endpoint` (one link),
`handlers` + `services` + `outputs` (message → what to do), `replies` (texts, pending
ACKs), `telemetry`, `budget`, `signing`, `tlog`.
"""
