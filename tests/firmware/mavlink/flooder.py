"""A hostile local peer: one pymavlink-packed frame sent over and over from its own socket.

    python -m tests.firmware.mavlink.flooder KIND HOST PORT FRAMES_PER_S SECONDS

KIND: `param_list` (PARAM_REQUEST_LIST to system 1) or `setpoint` (SET_ATTITUDE_TARGET, level,
hover thrust). Prints the frames it sent."""

from __future__ import annotations

import socket
import sys
import time

from pymavlink.dialects.v20 import common as M

from fcemu.firmware.params import ParamTable

HOVER = ParamTable()["MPC_THR_HOVER"]
BATCH = 100


def frame(kind: str) -> bytes:
    mav = M.MAVLink(None, srcSystem=66, srcComponent=191)
    if kind == "param_list":
        return mav.param_request_list_encode(1, 1).pack(mav)
    if kind == "setpoint":
        return mav.set_attitude_target_encode(0, 1, 1, 128, [1, 0, 0, 0], 0, 0, 0, HOVER).pack(mav)
    raise SystemExit(f"unknown kind {kind}")


def main(argv: list[str]) -> int:
    kind, host, port, rate, seconds = argv[1], argv[2], int(argv[3]), float(argv[4]), float(argv[5])
    data = frame(kind)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    start = time.monotonic()
    sent = 0
    while time.monotonic() - start < seconds:
        for _ in range(BATCH):
            try:
                sock.sendto(data, (host, port))
                sent += 1
            except OSError:
                pass
        ahead = start + sent / rate - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
    print(sent, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
