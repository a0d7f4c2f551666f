"""The PX4 ULog the firmware loop would write: the topics PX4 logs for system identification.

`ULogRecorder` is a telemetry sink of the flight loop; every tick it keeps what PX4's logger
keeps at the loop's rate with SDLOG_PROFILE's high-rate and system-identification bits:
`vehicle_angular_velocity` (the gyro the controller read), `vehicle_rates_setpoint`,
`actuator_motors` (the motor commands normalised 0..1 on the firmware's PWM scale),
`actuator_outputs` (the PWM, µs), `esc_status` (each ESC's telemetry rpm) and `actuator_armed`.
As in PX4, a topic's `timestamp` is when it was published and `timestamp_sample` the time of the
gyro sample it was computed from; the ESC telemetry is stamped with the time it was read.
Field names and types are those of PX4's msg/*.msg, so PX4's log tools read the file.
`write` hands the arrays to pyulog, which writes the file.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple, get_args, get_origin, get_type_hints

import numpy as np
from pyulog import ULog

from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.firmware.loop import TickSample

BOOT_US = 1_000_000  # PX4's tools read a timestamp of 0 as unset: the log starts a second after boot
RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
ESC_MAX = 8  # esc_status.CONNECTED_ESC_MAX
ESC_CONNECTION_TYPE_DSHOT = 5
ACTUATOR_FUNCTION_MOTOR1 = 101
CHUNK = 60_000  # ticks per block of memory: a minute at 1 kHz, 9 MB

# PX4's message definitions (msg/*.msg), as the logger writes their formats (padding left out).
FORMATS = {
    "vehicle_angular_velocity": "uint64_t timestamp;uint64_t timestamp_sample;float[3] xyz;"
                                "float[3] xyz_derivative;",
    "vehicle_rates_setpoint": "uint64_t timestamp;float roll;float pitch;float yaw;float[3] thrust_body;"
                              "bool reset_integral;",
    "actuator_motors": "uint64_t timestamp;uint64_t timestamp_sample;uint16_t reversible_flags;"
                       "float[8] control;",
    "actuator_outputs": "uint64_t timestamp;uint32_t noutputs;float[16] output;",
    "esc_report": "uint64_t timestamp;uint32_t esc_errorcount;int32_t esc_rpm;float esc_voltage;"
                  "float esc_current;float esc_temperature;uint8_t esc_address;uint8_t esc_cmdcount;"
                  "uint8_t esc_state;uint8_t actuator_function;uint16_t failures;int8_t esc_power;",
    "esc_status": "uint64_t timestamp;uint16_t counter;uint8_t esc_count;uint8_t esc_connectiontype;"
                  "uint8_t esc_online_flags;uint8_t esc_armed_flags;esc_report[8] esc;",
    "actuator_armed": "uint64_t timestamp;bool armed;bool prearmed;bool ready_to_arm;bool lockdown;"
                      "bool manual_lockdown;bool force_failsafe;bool in_esc_calibration_mode;",
}
TOPICS = ("vehicle_angular_velocity", "vehicle_rates_setpoint", "actuator_motors", "actuator_outputs",
          "esc_status", "actuator_armed")


class Row(NamedTuple):
    """What the recorder keeps of one tick, by name; `ROW_DTYPE`, the rows' numpy form, is built from it."""

    t_us: float  # when the tick published: every topic's timestamp
    gyro_t_us: float  # when the gyro sample the controller read was taken: the rates' timestamp_sample
    frame_t_us: float  # when the frame was taken: actuator_motors' timestamp_sample, esc_status's timestamp
    gyro: tuple[float, float, float]  # FRD rad/s
    rate_setpoint: tuple[float, float, float]  # FRD rad/s
    throttle: float  # 0..1
    pwm: tuple[float, float, float, float]  # µs
    rotor_speed: tuple[float, float, float, float]  # rad/s, as the ESCs reported them
    armed: float  # 1 armed, 0 not


def _row_dtype(cls: type) -> np.dtype:
    """float64 per field, a tuple field as one column of its length."""
    hints = get_type_hints(cls)
    return np.dtype([(name, np.float64, (len(get_args(hints[name])),)) if get_origin(hints[name]) is tuple
                     else (name, np.float64) for name in cls._fields])


ROW_DTYPE = _row_dtype(Row)


class _ArrayULog(ULog):
    """pyulog's ULog, its data messages packed from one numpy buffer per topic (pyulog packs each
    field of each sample with struct: minutes for a few minutes of 1 kHz flight)."""

    def _make_data_items(self) -> list[tuple[int, bytes]]:
        items: list[tuple[int, bytes]] = []
        for data_set in sorted(self._data_list, key=lambda d: d.msg_id):
            dtype = np.dtype([(f.field_name, self._UNPACK_TYPES[f.type_str][2])
                              for f in data_set.field_data]).newbyteorder("<")
            rows = np.empty(len(data_set.data["timestamp"]), dtype)
            for name in dtype.names or ():
                rows[name] = data_set.data[name]
            size = dtype.itemsize
            header = struct.pack("<HBH", size + 2, self.MSG_TYPE_DATA, data_set.msg_id)
            raw = rows.tobytes()
            stamps = data_set.data["timestamp"].tolist()
            items += [(stamps[i], header + raw[i * size:(i + 1) * size]) for i in range(len(rows))]
        return items


class ULogRecorder:
    """Keeps every tick's gyro, setpoint, motor commands and ESC rpm; `write` makes the ULog."""

    def __init__(self, boot_us: int = BOOT_US) -> None:
        self.boot_us = boot_us
        self._chunks: list[np.ndarray] = []  # ROW_DTYPE rows, CHUNK ticks each
        self._n = 0

    def publish(self, sample: TickSample) -> None:
        k = self._n % CHUNK
        if k == 0:
            self._chunks.append(np.empty(CHUNK, ROW_DTYPE))
        frame = sample.sensed or sample.frame  # the ESCs' rpm as reported, as PX4's esc_status logs it
        setpoint = sample.command.setpoint
        self._chunks[-1][k] = Row(
            t_us=sample.t_us, gyro_t_us=frame.gyro_t_us if frame.gyro_t_us is not None else frame.t_us,
            frame_t_us=frame.t_us, gyro=frame.gyro, rate_setpoint=setpoint.rates, throttle=setpoint.throttle,
            pwm=sample.pwm, rotor_speed=frame.rotor_speed, armed=sample.command.armed)
        self._n += 1

    def rows(self) -> np.ndarray:
        """Every tick recorded, (n,) of ROW_DTYPE."""
        return np.concatenate(self._chunks)[:self._n] if self._chunks else np.empty(0, ROW_DTYPE)

    def __len__(self) -> int:
        return self._n

    def topics(self) -> dict[str, dict[str, np.ndarray]]:
        """Each topic's fields as PX4 names them (nested ones flattened, `esc[0].esc_rpm`)."""
        if not self._n:
            raise ValueError("nothing was recorded: the loop never ticked")
        a = self.rows()
        n = len(a)
        t = (a["t_us"] + self.boot_us).astype(np.uint64)
        sampled = (a["frame_t_us"] + self.boot_us).astype(np.uint64)  # when the frame the tick read was taken
        gyro, rates, throttle = a["gyro"], a["rate_setpoint"], a["throttle"]
        pwm, rotor, armed = a["pwm"], a["rotor_speed"], a["armed"].astype(np.int8)
        zeros = np.zeros(n, np.float32)
        gyro_sampled = (a["gyro_t_us"] + self.boot_us).astype(np.uint64)
        gyro_vel: dict[str, np.ndarray] = {"timestamp": t, "timestamp_sample": gyro_sampled}
        for i in range(3):
            gyro_vel[f"xyz[{i}]"] = gyro[:, i].astype(np.float32)
            gyro_vel[f"xyz_derivative[{i}]"] = zeros
        setpoint = {"timestamp": t, "roll": rates[:, 0].astype(np.float32),
                    "pitch": rates[:, 1].astype(np.float32), "yaw": rates[:, 2].astype(np.float32),
                    "thrust_body[0]": zeros, "thrust_body[1]": zeros,
                    "thrust_body[2]": (-throttle).astype(np.float32), "reset_integral": np.zeros(n, np.int8)}
        control = ((pwm - PWM_MIN) / PWM_SPAN).astype(np.float32)
        motors = {"timestamp": t, "timestamp_sample": sampled, "reversible_flags": np.zeros(n, np.uint16)}
        for i in range(8):
            motors[f"control[{i}]"] = control[:, i] if i < 4 else np.full(n, np.nan, np.float32)
        outputs: dict[str, np.ndarray] = {"timestamp": t, "noutputs": np.full(n, 4, np.uint32)}
        for i in range(16):
            outputs[f"output[{i}]"] = pwm[:, i].astype(np.float32) if i < 4 else zeros
        esc = {"timestamp": sampled, "counter": (np.arange(n) % 65536).astype(np.uint16),
               "esc_count": np.full(n, 4, np.uint8),
               "esc_connectiontype": np.full(n, ESC_CONNECTION_TYPE_DSHOT, np.uint8),
               "esc_online_flags": np.full(n, 0x0F, np.uint8),
               "esc_armed_flags": np.where(armed > 0, 0x0F, 0).astype(np.uint8)}
        for i in range(ESC_MAX):
            live = i < 4
            report = {"timestamp": sampled if live else np.zeros(n, np.uint64),
                      "esc_errorcount": np.zeros(n, np.uint32),
                      "esc_rpm": np.rint(rotor[:, i] * RPM_PER_RAD_S).astype(np.int32) if live
                      else np.zeros(n, np.int32),
                      "esc_voltage": zeros, "esc_current": zeros, "esc_temperature": zeros,
                      "esc_address": np.full(n, i + 1 if live else 0, np.uint8),
                      "esc_cmdcount": np.zeros(n, np.uint8), "esc_state": np.zeros(n, np.uint8),
                      "actuator_function": np.full(n, ACTUATOR_FUNCTION_MOTOR1 + i if live else 0, np.uint8),
                      "failures": np.zeros(n, np.uint16),
                      "esc_power": (np.clip(control[:, i], 0, 1) * 100).astype(np.int8) if live
                      else np.zeros(n, np.int8)}
            esc.update({f"esc[{i}].{key}": value for key, value in report.items()})
        arm = {"timestamp": t, "armed": armed, "prearmed": armed, "ready_to_arm": np.ones(n, np.int8)}
        for key in ("lockdown", "manual_lockdown", "force_failsafe", "in_esc_calibration_mode"):
            arm[key] = np.zeros(n, np.int8)
        return {"vehicle_angular_velocity": gyro_vel, "vehicle_rates_setpoint": setpoint,
                "actuator_motors": motors, "actuator_outputs": outputs, "esc_status": esc,
                "actuator_armed": arm}

    def write(self, path: str | os.PathLike[str], info: dict[str, str] | None = None,
              topics: Sequence[str] = TOPICS) -> Path:
        """The ULog at `path` with `topics`; `info` adds string info messages (e.g. sys_name, ver_hw)."""
        log = _ArrayULog(None)
        log._file_version = 1
        log._start_timestamp = self.boot_us
        info = {"sys_name": "fcemu", "ver_hw": "SITL", **(info or {})}
        log._msg_info_dict = dict(info)
        log._msg_info_dict_types = {key: f"char[{len(value.encode())}]" for key, value in info.items()}
        log._message_formats = {name: ULog.MessageFormat(f"{name}:{fields}".encode(), None)
                                for name, fields in FORMATS.items()}
        kept = {name: fields for name, fields in self.topics().items() if name in topics}
        for msg_id, (name, fields) in enumerate(kept.items()):
            added = ULog._MessageAddLogged(struct.pack("<BH", 0, msg_id) + name.encode(), None,
                                           log._message_formats)
            rows = np.empty(len(fields["timestamp"]), added.dtype)
            for key in rows.dtype.names or ():
                rows[key] = fields[key]
            added.buffer = bytearray(rows.tobytes())
            log._data_list.append(ULog.Data(added))
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as handle:
            log.write_ulog(handle)
        return path
