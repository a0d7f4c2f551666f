"""`fcemu sitl --ulog`: the ULog pyulog reads back, with PX4's topic and field names at the loop rate."""

from __future__ import annotations

import numpy as np
from pyulog import ULog

from fcemu.cli import main
from fcemu.sitl.sitl import build_sitl
from fcemu.sitl.ulog_writer import BOOT_US, ROW_DTYPE, RPM_PER_RAD_S, TOPICS, Row, ULogRecorder


def _fly(seconds: float) -> tuple[ULogRecorder, object]:
    recorder = ULogRecorder()
    sitl = build_sitl("pid", rig="rig", realtime=False, sinks=[recorder])
    sitl.loop.run(seconds)
    return recorder, sitl


def test_every_topic_reads_back_at_the_loop_rate_with_what_the_loop_did(tmp_path) -> None:
    recorder, sitl = _fly(2.0)
    log = ULog(str(recorder.write(tmp_path / "flight.ulg")))
    assert sorted(d.name for d in log.data_list) == sorted(TOPICS)
    gyro = log.get_dataset("vehicle_angular_velocity").data
    t = gyro["timestamp"].astype(np.int64)
    assert len(t) == 2000 and t[0] == BOOT_US + 1000 and set(np.diff(t)) == {1000}
    assert set(t - gyro["timestamp_sample"].astype(np.int64)) == {1000}  # the frame the tick read
    motors_sampled = log.get_dataset("actuator_motors").data["timestamp_sample"]
    assert np.array_equal(motors_sampled, gyro["timestamp_sample"])
    assert np.abs(gyro["xyz[0]"]).max() > 1.0  # the scripted roll doublet
    sample = sitl.loop.last_sample
    assert np.allclose([gyro[f"xyz[{i}]"][-1] for i in range(3)], sample.frame.gyro, atol=1e-6)
    outputs = log.get_dataset("actuator_outputs").data
    assert np.allclose([outputs[f"output[{i}]"][-1] for i in range(4)], sample.pwm, atol=1e-3)
    motors = log.get_dataset("actuator_motors").data
    assert np.allclose(motors["control[0]"][-1], (sample.pwm[0] - 1000) / 1000, atol=1e-6)
    assert np.isnan(motors["control[4]"]).all()  # PX4: NaN marks an output that is no motor
    esc = log.get_dataset("esc_status").data
    rpm = [esc[f"esc[{i}].esc_rpm"][-1] for i in range(4)]
    assert np.allclose(rpm, sample.frame.rotor_speed * RPM_PER_RAD_S, atol=0.5)
    assert set(esc["esc[5].esc_rpm"]) == {0} and set(esc["esc_count"]) == {4}
    setpoint = log.get_dataset("vehicle_rates_setpoint").data
    assert setpoint["thrust_body[2]"][-1] == np.float32(-sample.command.setpoint.throttle)
    assert set(log.get_dataset("actuator_armed").data["armed"]) == {1}
    assert log.msg_info_dict["sys_name"] == "fcemu"


def test_fcemu_sitl_ulog_writes_the_file_and_refuses_one_it_cannot(tmp_path, capsys) -> None:
    path = tmp_path / "logs" / "sitl.ulg"
    assert main(["sitl", "--controller", "pid", "--rig", "rig", "--speed", "max", "--no-mavlink",
                 "--duration", "0.5", "--quiet", "--ulog", str(path)]) == 0
    assert len(ULog(str(path)).get_dataset("esc_status").data["timestamp"]) == 500
    assert main(["sitl", "--no-mavlink", "--duration", "0.1", "--ulog", str(tmp_path)]) == 2
    assert f"fcemu: error: --ulog {tmp_path}: cannot write it" in capsys.readouterr().err


def test_esc_status_is_the_rpm_the_escs_reported_not_the_firmwares_reading_ahead(tmp_path) -> None:
    recorder, sitl = _fly(0.2)
    last = sitl.loop.last_sample
    ahead = last.frame._replace(rotor_speed=last.frame.rotor_speed + 50.0)  # a late bus read ahead
    recorder.publish(last._replace(t_us=last.t_us + 1000, frame=ahead, sensed=last.frame))
    esc = ULog(str(recorder.write(tmp_path / "flight.ulg"))).get_dataset("esc_status").data
    rpm = [esc[f"esc[{i}].esc_rpm"][-1] for i in range(4)]
    assert np.allclose(rpm, last.frame.rotor_speed * RPM_PER_RAD_S, atol=0.5)
    assert last.sensed is not None  # the loop keeps what the sensors said beside what the controller read


def test_each_tick_is_kept_as_the_rows_declared_fields_by_name() -> None:
    assert ROW_DTYPE.names == Row._fields
    assert {name: ROW_DTYPE[name].shape for name in Row._fields} == {
        "t_us": (), "gyro_t_us": (), "frame_t_us": (), "gyro": (3,), "rate_setpoint": (3,), "throttle": (),
        "pwm": (4,), "rotor_speed": (4,), "armed": ()}
    recorder, sitl = _fly(0.05)
    rows, last = recorder.rows(), sitl.loop.last_sample
    assert rows.dtype == ROW_DTYPE and len(rows) == len(recorder) == 50
    row = rows[-1]
    assert row["t_us"] == last.t_us and row["frame_t_us"] == last.frame.t_us
    assert row["gyro_t_us"] == (last.frame.gyro_t_us if last.frame.gyro_t_us is not None else last.frame.t_us)
    assert np.array_equal(row["gyro"], last.frame.gyro)
    assert np.array_equal(row["rate_setpoint"], last.command.setpoint.rates)
    assert row["throttle"] == last.command.setpoint.throttle and row["armed"] == 1.0
    assert np.array_equal(row["pwm"], last.pwm)
    assert np.array_equal(row["rotor_speed"], (last.sensed or last.frame).rotor_speed)


def test_the_ulog_fields_are_the_rows_fields_by_name(tmp_path) -> None:
    recorder, _ = _fly(0.3)
    rows = recorder.rows()
    log = ULog(str(recorder.write(tmp_path / "flight.ulg")))
    data = {d.name: d.data for d in log.data_list}
    t = (rows["t_us"] + BOOT_US).astype(np.uint64)
    gyro = data["vehicle_angular_velocity"]
    assert np.array_equal(gyro["timestamp"], t)
    assert np.array_equal(gyro["timestamp_sample"], (rows["gyro_t_us"] + BOOT_US).astype(np.uint64))
    assert np.array_equal(data["esc_status"]["timestamp"], (rows["frame_t_us"] + BOOT_US).astype(np.uint64))
    setpoint = data["vehicle_rates_setpoint"]
    for i, axis in enumerate(("roll", "pitch", "yaw")):
        assert np.array_equal(gyro[f"xyz[{i}]"], rows["gyro"][:, i].astype(np.float32))
        assert np.array_equal(setpoint[axis], rows["rate_setpoint"][:, i].astype(np.float32))
    assert np.array_equal(setpoint["thrust_body[2]"], (-rows["throttle"]).astype(np.float32))
    for i in range(4):
        assert np.array_equal(data["actuator_outputs"][f"output[{i}]"], rows["pwm"][:, i].astype(np.float32))
        rpm = np.rint(rows["rotor_speed"][:, i] * RPM_PER_RAD_S).astype(np.int32)
        assert np.array_equal(data["esc_status"][f"esc[{i}].esc_rpm"], rpm)
    assert np.array_equal(data["actuator_armed"]["armed"], rows["armed"].astype(np.uint8))
