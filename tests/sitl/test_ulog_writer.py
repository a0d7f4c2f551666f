"""`fcemu sitl --ulog`: the ULog pyulog reads back, with PX4's topic and field names at the loop rate."""

from __future__ import annotations

import numpy as np
from pyulog import ULog

from fcemu.cli import main
from fcemu.sitl.sitl import build_sitl
from fcemu.sitl.ulog_writer import BOOT_US, RPM_PER_RAD_S, TOPICS, ULogRecorder


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
