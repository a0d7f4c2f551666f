"""A peer for `fcemu bench loop --mavlink`: listens where the vehicle sends telemetry (GCS and
offboard ports) and parses all of it, arms the vehicle, puts it in OFFBOARD and streams
SET_ATTITUDE_TARGET body rates at 100 Hz (a slow sine on each axis at hover thrust) until killed.

    python -m fcemu.benchmarks.loadpeer GCS_PORT OFFBOARD_PORT [RATE_HZ]
"""

from __future__ import annotations

import math
import sys
import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M


def main(argv: list[str]) -> int:
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{int(argv[1])}", source_system=255)
    off = mavutil.mavlink_connection(f"udpin:127.0.0.1:{int(argv[2])}", source_system=245,
                                     source_component=190)
    rate = float(argv[3]) if len(argv) > 3 else 100.0
    off.wait_heartbeat(timeout=30)
    t0 = time.monotonic()
    k = 0
    received = 0
    while True:
        t = time.monotonic() - t0
        s = 0.5 * math.sin(2 * math.pi * 0.5 * t)
        off.mav.set_attitude_target_send(int(t * 1000) & 0xFFFFFFFF, 1, 1, 128, [1, 0, 0, 0],
                                         s, -s, 0.5 * s, 0.74)
        if k % int(rate) == 0:
            off.mav.heartbeat_send(M.MAV_TYPE_ONBOARD_CONTROLLER, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            gcs.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        if k == 5:
            off.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
        if k == 10:
            off.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        k += 1
        deadline = t0 + k / rate
        while (now := time.monotonic()) < deadline:
            for conn in (gcs, off):
                while conn.recv_match(blocking=False) is not None:
                    received += 1
            time.sleep(min(0.002, max(0.0, deadline - now)))


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv))
    except KeyboardInterrupt:
        sys.exit(0)
