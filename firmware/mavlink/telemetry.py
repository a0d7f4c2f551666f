"""Telemetry: what each stream says, built from the flight process's latest snapshot, and
when it is due. Intervals are in loop time (the vehicle's clock, like PX4 in lockstep), so a
script flying the SITL faster than real time still gets its ATTITUDE at the rate it asked;
HEARTBEAT alone is paced in wall time by the process."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.estimator import euler_from_quat
from fcemu.firmware.mavlink.ipc import Snapshot
from fcemu.firmware.vehicle import ACRO, AUTO, MANUAL, OFFBOARD, STABILIZED

M = mavlink
HOME = (473977420, 85455940, 488000)  # PX4 SITL's default home (Zurich), 1e7 deg, mm
PX4_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 0xFF  # reported as PX4 1.15.0 release

# MAV_SYS_STATUS_SENSOR bits MAVSDK and QGC read for health.
SENSORS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_AHRS
           | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | M.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
           | M.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION)
PREARM = M.MAV_SYS_STATUS_PREARM_CHECK

CAPABILITIES = (M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | M.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT)

# Default streams (message id → interval in µs of loop time).
DEFAULT_INTERVALS = {
    M.MAVLINK_MSG_ID_SYS_STATUS: 500_000,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 500_000,
    M.MAVLINK_MSG_ID_ATTITUDE: 20_000,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20_000,
    M.MAVLINK_MSG_ID_HIGHRES_IMU: 20_000,
    M.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 100_000,
    M.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS: 100_000,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 33_333,
    M.MAVLINK_MSG_ID_HOME_POSITION: 2_000_000,
}
MIN_INTERVAL_US = 4_000  # snapshots come at 250 Hz of loop time; nothing streams faster


def base_mode(snap: Snapshot) -> int:
    main = (snap.custom_mode >> 16) & 0xFF
    mode = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if snap.armed:
        mode |= M.MAV_MODE_FLAG_SAFETY_ARMED
    if main in (MANUAL, STABILIZED, ACRO):
        mode |= M.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if main in (MANUAL, STABILIZED):
        mode |= M.MAV_MODE_FLAG_STABILIZE_ENABLED
    if main == OFFBOARD:
        mode |= M.MAV_MODE_FLAG_GUIDED_ENABLED
    if main == AUTO:
        mode |= M.MAV_MODE_FLAG_AUTO_ENABLED | M.MAV_MODE_FLAG_STABILIZE_ENABLED
    return mode


def heartbeat(mav, snap: Snapshot):
    status = (M.MAV_STATE_CRITICAL if snap.failsafe else M.MAV_STATE_ACTIVE if snap.armed
              else M.MAV_STATE_STANDBY)
    return mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base_mode(snap),
                                snap.custom_mode, status)


def build(msgid: int, mav, snap: Snapshot, load: int = 0):
    """The message `msgid` as of `snap`, or None if this vehicle does not send it."""
    t_ms = (snap.t_us // 1000) & 0xFFFFFFFF
    if msgid == M.MAVLINK_MSG_ID_ATTITUDE:
        roll, pitch, yaw = euler_from_quat(snap.q)
        return mav.attitude_encode(t_ms, roll, pitch, yaw, *snap.gyro)
    if msgid == M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
        return mav.attitude_quaternion_encode(t_ms, *snap.q, *snap.gyro, [0.0] * 4)
    if msgid == M.MAVLINK_MSG_ID_HIGHRES_IMU:
        return mav.highres_imu_encode(snap.t_us, *snap.accel, *snap.gyro, 0, 0, 0, 0, 0, 0, 25.0,
                                      0b111111, 0)
    if msgid == M.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
        pwm = [round(p) for p in snap.pwm]
        return mav.servo_output_raw_encode(snap.t_us & 0xFFFFFFFF, 0, *pwm, 0, 0, 0, 0, *[0] * 8)
    if msgid == M.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS:
        return mav.actuator_output_status_encode(snap.t_us, 0b1111, [*snap.pwm, *[0.0] * 28])
    if msgid == M.MAVLINK_MSG_ID_SYS_STATUS:
        health = SENSORS | (PREARM if snap.armable or snap.armed else 0)
        if snap.failsafe:
            health &= ~M.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
        return mav.sys_status_encode(SENSORS | PREARM, SENSORS | PREARM, health, load, 16_200, -1, -1,
                                     0, 0, 0, 0, 0, 0)
    if msgid == M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
        return mav.extended_sys_state_encode(M.MAV_VTOL_STATE_MC, snap.landed_state)
    if msgid == M.MAVLINK_MSG_ID_HOME_POSITION:
        return mav.home_position_encode(*HOME, 0, 0, 0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, snap.t_us)
    if msgid == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
        if not snap.has_position:
            return None
        return mav.local_position_ned_encode(t_ms, *snap.position, *snap.velocity)
    if msgid == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
        return mav.autopilot_version_encode(CAPABILITIES, PX4_VERSION, 0, 0, 1, [0] * 8, [0] * 8,
                                            [0] * 8, 0x26AC, 0x1, 0xFCE0_0001, [0] * 18)
    return None


STATUSTEXT_LEN = 50
STATUSTEXT_MAX_CHUNKS = 4


def statustext(mav, severity: int, text: str, text_id: int) -> list:
    """STATUSTEXT for `text`: one message if it fits in 50 bytes, else MAVLink 2 chunks (same
    `id`, `chunk_seq` from 0; a chunk shorter than 50 bytes, if need be an empty one, ends it)."""
    data = text.encode()[:STATUSTEXT_LEN * STATUSTEXT_MAX_CHUNKS].decode(errors="ignore").encode()
    if len(data) <= STATUSTEXT_LEN:
        return [mav.statustext_encode(severity, data, 0, 0)]
    chunks = [data[i:i + STATUSTEXT_LEN] for i in range(0, len(data), STATUSTEXT_LEN)]
    if len(chunks[-1]) == STATUSTEXT_LEN:
        chunks.append(b"")
    return [mav.statustext_encode(severity, chunk, text_id, seq) for seq, chunk in enumerate(chunks)]


STREAMABLE = frozenset(DEFAULT_INTERVALS)
REQUESTABLE = STREAMABLE | {M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, M.MAVLINK_MSG_ID_HEARTBEAT}


class Scheduler:
    """Per-link stream intervals (SET_MESSAGE_INTERVAL changes them) and when each is due."""

    def __init__(self, has_position: bool) -> None:
        self.intervals = dict(DEFAULT_INTERVALS)
        if not has_position:
            self.intervals.pop(M.MAVLINK_MSG_ID_LOCAL_POSITION_NED)
        self._next: dict[int, int] = {}

    def set_interval(self, msgid: int, interval_us: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL semantics: -1 stops, 0 restores the default."""
        if msgid not in STREAMABLE or not math.isfinite(interval_us):
            return False
        if interval_us < 0:
            self.intervals.pop(msgid, None)
        elif interval_us == 0:
            self.intervals[msgid] = DEFAULT_INTERVALS[msgid]
        else:
            self.intervals[msgid] = max(int(interval_us), MIN_INTERVAL_US)
        self._next.pop(msgid, None)
        return True

    def interval(self, msgid: int) -> int:
        return self.intervals.get(msgid, -1)

    def due(self, t_us: int) -> list[int]:
        out = []
        nxt = self._next
        for msgid, interval in self.intervals.items():
            when = nxt.get(msgid)
            if when is None or t_us >= when or t_us < when - 2 * interval:  # (clock restarted)
                out.append(msgid)
                on_grid = when is not None and t_us - when < interval
                nxt[msgid] = when + interval if on_grid else t_us + interval
        return out
