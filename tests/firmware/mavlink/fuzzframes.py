"""Hostile MAVLink input for the fuzz test: frames pymavlink builds with values the vehicle must
refuse, valid frames for another system, frames with flipped bytes, cut short or with a wrong
CRC, correctly framed random payloads, and plain random bytes.

Nothing generated here may be a valid request to the vehicle under test (system 1, component
1 or 0): the test checks afterwards that the vehicle's state and parameters are unchanged."""

from __future__ import annotations

import math
import random
import struct

from pymavlink.dialects.v20 import common as M

BAD_RATES = (math.nan, math.inf, -math.inf, 35.5, -40.0, 1e9, -1e30)
BAD_THRUST = (math.nan, math.inf, -0.01, 1.01, 7.0, -1e9)
BAD_PARAMS = (math.nan, math.inf, -math.inf, -1e12, 1e12)
KNOWN_PARAMS = (b"COM_OF_LOSS_T", b"PID_ROLL_P", b"CTRL_SEL", b"RATE_R_MAX", b"FS_DESC_SPD",
                b"IMU_DGYRO_CUTOFF")
# Message ids a correctly framed random payload could turn into a real request: only the
# deliberate generators below produce these (with values that are refused).
ACTIONABLE = {M.MAVLINK_MSG_ID_SET_MODE, M.MAVLINK_MSG_ID_COMMAND_LONG, M.MAVLINK_MSG_ID_COMMAND_INT,
              M.MAVLINK_MSG_ID_PARAM_SET, M.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET,
              M.MAVLINK_MSG_ID_MANUAL_CONTROL, M.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE,
              M.MAVLINK_MSG_ID_PARAM_REQUEST_LIST}
HANDLED_COMMANDS = {M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_NAV_LAND,
                    M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                    M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAV_CMD_GET_MESSAGE_INTERVAL}
UNHANDLED_COMMANDS = [c for c in range(1, 1000) if c not in HANDLED_COMMANDS]


class FrameFuzzer:
    def __init__(self, seed: int = 0, target: int = 1) -> None:
        self.rng = random.Random(seed)
        self.target = target
        self.mav = M.MAVLink(None, srcSystem=201, srcComponent=1)
        self._ids = sorted(set(M.mavlink_map) - ACTIONABLE)
        self.kinds = {"refused": 0, "foreign": 0, "flipped": 0, "truncated": 0, "bad_crc": 0,
                      "random_payload": 0, "random_bytes": 0}

    # ---- frames pymavlink encodes, with values the vehicle must refuse ----
    def refused(self) -> M.MAVLink_message:
        r, mav, t = self.rng, self.mav, self.target
        kind = r.randrange(6)
        if kind == 0:
            rates = [r.choice(BAD_RATES) if r.random() < 0.5 else r.uniform(-3, 3) for _ in range(3)]
            if all(math.isfinite(v) and abs(v) <= 35 for v in rates):
                rates[r.randrange(3)] = r.choice(BAD_RATES)
            thrust = r.choice(BAD_THRUST) if r.random() < 0.5 else r.uniform(0, 1)
            return mav.set_attitude_target_encode(0, t, 1, 128 | r.choice((0, 1, 2, 4, 64)), [1, 0, 0, 0],
                                                  *rates, thrust)
        if kind == 1:
            values = [r.randint(-1000, 1000), r.randint(-1000, 1000), r.randint(0, 1000),
                      r.randint(-1000, 1000)]
            bad = r.randrange(4)  # x, y, r beyond ±1000; z (throttle) below 0 or beyond 1000
            values[bad] = r.choice((r.randint(1001, 32767), r.randint(-32768, -1001 if bad != 2 else -1)))
            return mav.manual_control_encode(t, *values, 0)
        if kind == 2:
            if r.random() < 0.7:
                name = r.choice(KNOWN_PARAMS)
                value = r.choice(BAD_PARAMS)
            else:
                name = bytes(r.randint(33, 126) for _ in range(r.randint(1, 16)))
                name = b"ZZ" + name[2:] if len(name) > 2 else b"ZZZ"  # no real parameter starts so
                value = r.uniform(-10, 10)
            return mav.param_set_encode(t, 1, name, value, r.choice((M.MAV_PARAM_TYPE_REAL32,
                                                                      M.MAV_PARAM_TYPE_INT32)))
        if kind == 3:
            cmd, params = r.choice((
                (M.MAV_CMD_COMPONENT_ARM_DISARM, (r.choice((math.nan, math.inf, 2.0, -1.0, 0.5, 1e9)), 0)),
                (M.MAV_CMD_DO_SET_MODE, (1, r.choice((math.nan, math.inf, 256.0, -1.0, 1e12)), 0)),
                (M.MAV_CMD_DO_SET_MODE, (r.choice((math.nan, -math.inf)), 5, 0)),
                (M.MAV_CMD_REQUEST_MESSAGE, (r.choice((math.nan, math.inf, -5.0, 1e30)),)),
                (M.MAV_CMD_SET_MESSAGE_INTERVAL, (30, r.choice((math.nan, math.inf)))),
                (r.choice(UNHANDLED_COMMANDS), tuple(r.choice((*BAD_PARAMS, 0.0, 1.0)) for _ in range(7))),
            ))
            p = [*params, *[r.choice((0.0, math.nan)) for _ in range(7)]][:7]
            return mav.command_long_encode(t, 1, cmd, r.randint(0, 255), *p)
        if kind == 4:
            ch = [r.choice((r.randint(1, 799), r.randint(2201, 65534))) for _ in range(4)]
            return mav.rc_channels_override_encode(t, 1, *ch, *[0] * 14)
        return mav.set_attitude_target_encode(0, t, 1, r.choice((0, 1, 7)), [1, 0, 0, 0], 0, 0, 0, 0.5)

    # ---- valid requests, addressed to another system or component ----
    def foreign(self) -> M.MAVLink_message:
        r, mav = self.rng, self.mav
        system, comp = (r.randint(2, 255), 1) if r.random() < 0.7 else (self.target, r.randint(2, 255))
        kind = r.randrange(5)
        if kind == 0:
            return mav.command_long_encode(system, comp, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, r.randint(0, 1),
                                           0, 0, 0, 0, 0, 0)
        if kind == 1:
            return mav.command_long_encode(system, comp, M.MAV_CMD_DO_SET_MODE, 0, 1, r.choice((1, 5, 7)),
                                           0, 0, 0, 0, 0)
        if kind == 2:
            return mav.set_attitude_target_encode(0, system, comp, 128, [1, 0, 0, 0], 3.0, -3.0, 1.0, 0.2)
        if kind == 3:
            return mav.param_set_encode(system, comp, b"COM_OF_LOSS_T", 0.3, M.MAV_PARAM_TYPE_REAL32)
        return mav.rc_channels_override_encode(system, comp, 1500, 1500, 1900, 1500, *[0] * 14)

    # ---- framing damage ----
    def frame(self) -> bytes:
        r = self.rng
        roll = r.random()
        if roll < 0.25:
            self.kinds["refused"] += 1
            return self.refused().pack(self.mav)
        if roll < 0.35:
            self.kinds["foreign"] += 1
            return self.foreign().pack(self.mav)
        base = bytearray(self.refused().pack(self.mav) if r.random() < 0.5 else self.foreign().pack(self.mav))
        if roll < 0.50:
            self.kinds["flipped"] += 1
            for _ in range(r.randint(1, 3)):
                base[r.randrange(len(base))] ^= 1 << r.randrange(8)
            return bytes(base)
        if roll < 0.60:
            self.kinds["truncated"] += 1
            return bytes(base[:r.randrange(1, len(base))])
        if roll < 0.70:
            self.kinds["bad_crc"] += 1
            base[-1] ^= r.randint(1, 255)
            return bytes(base)
        if roll < 0.85:
            self.kinds["random_payload"] += 1
            return self.random_payload()
        self.kinds["random_bytes"] += 1
        data = bytes(r.getrandbits(8) for _ in range(r.randint(1, 280)))
        return (bytes([r.choice((0xFD, 0xFE))]) + data) if r.random() < 0.5 else data

    def random_payload(self) -> bytes:
        """A correctly framed MAVLink 2 message of a random non-actionable type, random payload."""
        r = self.rng
        msgid = r.choice(self._ids)
        cls = M.mavlink_map[msgid]
        length = r.randint(1, cls.unpacker.size)
        payload = bytes(r.getrandbits(8) for _ in range(length))
        header = struct.pack("<BBBBBBBHB", 0xFD, length, 0, 0, r.randrange(256), 201, 1, msgid & 0xFFFF,
                             msgid >> 16)
        crc = M.x25crc(header[1:] + payload)
        crc.accumulate(struct.pack("B", cls.crc_extra))
        return header + payload + struct.pack("<H", crc.crc)

    def datagram(self, max_frames: int = 6) -> tuple[bytes, int]:
        n = self.rng.randint(1, max_frames)
        return b"".join(self.frame() for _ in range(n)), n
