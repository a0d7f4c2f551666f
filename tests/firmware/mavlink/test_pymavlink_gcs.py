"""A pymavlink ground station against the real SITL: identity, commands, params, streams, tlog."""

from __future__ import annotations

import struct

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import command, connect, wait_for

pytestmark = pytest.mark.timeout(90)


def param_value(conn, name: str) -> float:
    return wait_for(conn, "PARAM_VALUE", lambda m: m.param_id == name).param_value


def test_px4_identity_commands_params_and_tlog(sitl, tmp_path) -> None:
    s = sitl()
    gcs = connect(s.gcs_port)
    hb = gcs.messages["HEARTBEAT"]
    assert (hb.type, hb.autopilot, hb.get_srcComponent()) == (2, 12, 1)
    assert gcs.flightmode == "STABILIZED"
    # every telemetry stream the issue names
    for kind in ("SYS_STATUS", "ATTITUDE", "ATTITUDE_QUATERNION", "HIGHRES_IMU", "SERVO_OUTPUT_RAW",
                 "ACTUATOR_OUTPUT_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION", "LOCAL_POSITION_NED"):
        wait_for(gcs, kind, timeout=5)
    status = wait_for(gcs, "SYS_STATUS")
    gyro_accel = M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    assert status.onboard_control_sensors_health & gyro_accel == gyro_accel
    # requests
    assert command(gcs, M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION).result == 0
    ver = wait_for(gcs, "AUTOPILOT_VERSION")
    assert ver.capabilities & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert command(gcs, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 5000).result == 0
    assert command(gcs, M.MAV_CMD_GET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE).result == 0
    assert wait_for(gcs, "MESSAGE_INTERVAL").interval_us == 5000
    assert command(gcs, M.MAV_CMD_NAV_TAKEOFF).result == M.MAV_RESULT_UNSUPPORTED
    assert command(gcs, M.MAV_CMD_REQUEST_MESSAGE, 9999).result == M.MAV_RESULT_UNSUPPORTED
    # modes: PX4 custom modes by name; OFFBOARD refused without a setpoint stream
    gcs.set_mode_px4("ACRO", None, None)
    assert wait_for(gcs, "COMMAND_ACK", lambda m: m.command == M.MAV_CMD_DO_SET_MODE).result == 0
    wait_for(gcs, "HEARTBEAT", lambda m: mavutil.interpret_px4_mode(m.base_mode, m.custom_mode) == "ACRO")
    gcs.set_mode_px4("OFFBOARD", None, None)
    ack = wait_for(gcs, "COMMAND_ACK", lambda m: m.command == M.MAV_CMD_DO_SET_MODE)
    assert ack.result == M.MAV_RESULT_DENIED
    # arming: throttle must be low; then armed shows in the heartbeat
    gcs.mav.manual_control_send(1, 0, 0, 600, 0, 0)
    assert command(gcs, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_DENIED
    gcs.mav.manual_control_send(1, 0, 0, 0, 0, 0)  # reaches the vehicle before the ARM that follows
    assert command(gcs, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    wait_for(gcs, "HEARTBEAT", lambda m: m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
    assert command(gcs, M.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == 0
    # parameters: list, read, set, bad value refused with the current value and a STATUSTEXT
    gcs.mav.param_request_list_send(1, 1)
    names = set()
    while True:
        pv = wait_for(gcs, "PARAM_VALUE")
        names.add(pv.param_id)
        if len(names) == pv.param_count:
            break
    assert {"COM_OF_LOSS_T", "PID_ROLL_P", "RATE_R_MAX", "CTRL_SEL", "IMU_DGYRO_CUTOFF"} <= names
    gcs.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.8, M.MAV_PARAM_TYPE_REAL32)
    assert param_value(gcs, "COM_OF_LOSS_T") == pytest.approx(0.8)
    gcs.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", float("nan"), M.MAV_PARAM_TYPE_REAL32)
    assert param_value(gcs, "COM_OF_LOSS_T") == pytest.approx(0.8)
    assert "rejected" in wait_for(gcs, "STATUSTEXT", lambda m: "Param" in m.text).text
    gcs.mav.param_request_read_send(1, 1, b"CTRL_SEL", -1)
    pv = wait_for(gcs, "PARAM_VALUE", lambda m: m.param_id == "CTRL_SEL")
    assert pv.param_type == M.MAV_PARAM_TYPE_INT32
    assert struct.unpack("<i", struct.pack("<f", pv.param_value))[0] == 0  # PX4's bytewise INT32
    # empty mission, timesync
    gcs.mav.mission_request_list_send(1, 1, 0)
    assert wait_for(gcs, "MISSION_COUNT").count == 0
    gcs.mav.timesync_send(0, 12345)
    assert wait_for(gcs, "TIMESYNC", lambda m: m.ts1 == 12345).tc1 > 0
    # foreign-system and malformed input is counted, not acted on
    gcs.mav.command_long_send(7, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    gcs.mav.set_attitude_target_send(0, 1, 1, 128, [1, 0, 0, 0], float("nan"), 0, 0, 0.5)
    assert wait_for(gcs, "NAMED_VALUE_INT", lambda m: m.name == "rx_foreign" and m.value >= 1, timeout=5)
    assert wait_for(gcs, "NAMED_VALUE_INT", lambda m: m.name == "rx_rejecte" and m.value >= 2, timeout=5)
    out = s.stop()
    assert "misses" in out
    # the parameter persisted, and survives a restart
    s2 = sitl()
    gcs2 = connect(s2.gcs_port)
    gcs2.mav.param_request_read_send(1, 1, b"COM_OF_LOSS_T", -1)
    assert param_value(gcs2, "COM_OF_LOSS_T") == pytest.approx(0.8)
    # the session tlog opens with pymavlink's reader (what mavlogdump and MAVExplorer use)
    log = mavutil.mavlink_connection(str(s.tlog))
    kinds = set()
    while (m := log.recv_match()) is not None:
        kinds.add(m.get_type())
    assert {"HEARTBEAT", "ATTITUDE", "COMMAND_LONG", "COMMAND_ACK", "PARAM_SET"} <= kinds
