"""MAVLink for the vehicle, in two halves.

The flight process imports only `bridge` and `ipc` (no pymavlink): the vehicle state, the
failsafe and the estimator stay in the 1 kHz loop. Everything that parses or encodes
MAVLink (`process`, `endpoint`, `handlers`, `telemetry`, `tlog`) runs in a separate
process, started by `bridge.start_mavlink`, so it never competes with the loop for the GIL.
"""
