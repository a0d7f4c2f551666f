"""The twin as Betaflight SITL's simulator: its UDP packets, and a real-time bridge that serves them.

Packet layouts are Betaflight 4.6's (`src/platform/SIMULATOR/target/SITL/target.h`, `sitl.c`):

- FDM state, us → SITL on UDP 9003: `fdm_packet`, 18 little-endian doubles: timestamp (s),
  angular velocity (3), linear acceleration (3), orientation quaternion (w, x, y, z),
  velocity (3), position (3), pressure (Pa).
  A firmware built by `fcemu export --target betaflight` also takes the extended packet,
  `FDM_PACKET_RPM`: the same 18 doubles and the four rotor speeds in rpm, Betaflight motor
  order, which its SITL serves as the bidirectional DShot telemetry (`getDshotRpm`) the
  NEURAL mode reads. Stock Betaflight accepts only the 144-byte packet.
  Each step carries one telemetry frame per motor, as bidirectional DShot answers each motor
  update: a motor whose frame was lost (the twin's sample did not advance, a dropped or stopped
  ESC telemetry; or its reading is not finite) is sent as NaN, which that SITL counts as an
  invalid frame, keeping the motor's last valid rpm (`telemetry_frames`). A delayed sample goes
  out when it arrives, as a valid frame: the firmware sees it late, as it would on a board.
  That SITL takes a lost gyro sample the same way (`gyro_sample`: NaN, and its gyro driver reads
  nothing new); stock Betaflight gets the twin's gyro as it is.
- RC, us → SITL on UDP 9004: `rc_packet`, timestamp (s) and 16 uint16 channels (µs), AETR1234.
- Motors, SITL → us on UDP 9002: `servo_packet`, 4 floats, (µs − mincommand) / 1000.

Axes and signs. The SITL takes the angular velocity in FRD (it negates y and z into its own
FLU sensor frame), so the twin's gyro goes out as it is. It negates all three accelerometer
components (`-acc * 256/g`), which is right for z only: our FRD specific force f is sent as
(−f_x, f_y, f_z) so that Betaflight's accelerometer reads (f_x, −f_y, −f_z) in its FLU frame,
like its gyro. The quaternion (FRD body → NED) goes to `imuSetAttitudeQuat` unchanged: with
`USE_IMU_CALC` undefined the SITL takes its attitude from it.

Motor order. `pwmCompleteMotorUpdate` writes ArduCopter's order into the packet
(`motor_speed[3] = motor 1, [0] = motor 2, [1] = motor 3, [2] = motor 4`); `unpack_motors`
undoes that, so the result is in Betaflight's (and our) Quad X order: 1 rear-right,
2 front-right, 3 rear-left, 4 front-left.

Timing. The SITL is not lockstep: its clock runs at wall time scaled by the ratio of FDM
timestamp steps to their arrival intervals (taken from each pair of packets alone), and it
answers each FDM packet with exactly one motor packet, at its next motor update.
`BetaflightBridge` paces the twin on real time (or `speed` × real time) as a ceiling: one FDM
packet per twin step, then it waits for the answer. An answer that comes after the next step
was due is "late": the bridge waits for it rather than send the next packet (two packets
queued at the SITL would be read back to back and make its clock race), so sim time slows
down for that step and the grid moves on, never catching up in a burst. No answer within
`reply_timeout_s` is "lost": that step flies on the previous motor values.
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from fcemu.firmware.sensors import SensorFrame

FDM_PORT = 9003
RC_PORT = 9004
MOTOR_PORT = 9002
CLI_PORT = 5761

FDM_PACKET = struct.Struct("<d3d3d4d3d3dd")  # 144 bytes
FDM_PACKET_RPM = struct.Struct("<d3d3d4d3d3dd4d")  # 176 bytes: + rotor speeds, rpm
RAD_S_TO_RPM = 60.0 / (2.0 * np.pi)
RC_CHANNELS = 16
RC_PACKET = struct.Struct(f"<d{RC_CHANNELS}H")  # 40 bytes
MOTOR_PACKET = struct.Struct("<4f")  # 16 bytes

MINCOMMAND_US = 1000.0  # Betaflight's motor mincommand: the offset the SITL takes off before /1000
SEA_LEVEL_PA = 101325.0
# servo_packet index of Betaflight motors 1..4 (ArduCopter order in the packet).
_PACKET_INDEX = (3, 0, 1, 2)

# Betaflight's default channel map AETR1234: roll, pitch, throttle, yaw, then AUX1...
ROLL_CH, PITCH_CH, THROTTLE_CH, YAW_CH, AUX1_CH = 0, 1, 2, 3, 4


def pack_fdm(timestamp_s: float, gyro_frd: Sequence[float], accel_frd: Sequence[float],
             quat_wxyz: Sequence[float], velocity_ned: Sequence[float] = (0.0, 0.0, 0.0),
             position_ned: Sequence[float] = (0.0, 0.0, 0.0), pressure_pa: float = SEA_LEVEL_PA,
             rotor_speed: Sequence[float] | None = None) -> bytes:
    """One FDM packet from the twin's FRD gyro (rad/s), FRD specific force (m/s²) and attitude;
    with `rotor_speed` (rad/s, motor order) the extended packet carrying them in rpm."""
    fx, fy, fz = accel_frd
    values = (float(timestamp_s), *map(float, gyro_frd), -float(fx), float(fy), float(fz),
              *map(float, quat_wxyz), *map(float, velocity_ned), *map(float, position_ned),
              float(pressure_pa))
    if rotor_speed is None:
        return FDM_PACKET.pack(*values)
    return FDM_PACKET_RPM.pack(*values, *(float(w) * RAD_S_TO_RPM for w in rotor_speed))


def telemetry_frames(frame: SensorFrame, last_sampled_us: np.ndarray | None) -> np.ndarray:
    """The rotor speeds (rad/s) to send for `frame`: NaN for each motor whose sample is not newer than
    the one sent before (`last_sampled_us`, None: no earlier times known) or not finite."""
    speed = np.array(frame.rotor_speed, dtype=float)
    if frame.rotor_speed_t_us is not None and last_sampled_us is not None:
        speed[np.asarray(frame.rotor_speed_t_us) <= last_sampled_us] = np.nan
    return speed


def gyro_sample(frame: SensorFrame, last_sampled_us: int | None) -> np.ndarray:
    """The gyro (FRD rad/s) to send for `frame`: NaN if its sample is not newer than the one sent
    before (`last_sampled_us`, None: no earlier time known)."""
    sampled = frame.gyro_t_us
    if sampled is not None and last_sampled_us is not None and sampled <= last_sampled_us:
        return np.full(3, np.nan)
    return np.asarray(frame.gyro, dtype=float)


def unpack_fdm(data: bytes) -> dict[str, object]:
    """The fields of an FDM packet, as sent (for tests and debugging)."""
    v = (FDM_PACKET_RPM if len(data) == FDM_PACKET_RPM.size else FDM_PACKET).unpack(data)
    out = {"timestamp": v[0], "gyro": v[1:4], "accel": v[4:7], "quat": v[7:11],
           "velocity": v[11:14], "position": v[14:17], "pressure": v[17]}
    if len(v) > 18:
        out["rotor_rpm"] = v[18:22]
    return out


def pack_rc(timestamp_s: float, channels: Sequence[int]) -> bytes:
    """One RC packet; missing channels are 1000 µs (a switch low)."""
    if len(channels) > RC_CHANNELS:
        raise ValueError(f"at most {RC_CHANNELS} RC channels, got {len(channels)}")
    values = [min(max(round(c), 0), 65535) for c in channels]
    values += [1000] * (RC_CHANNELS - len(values))
    return RC_PACKET.pack(float(timestamp_s), *values)


def unpack_motors(data: bytes) -> tuple[float, float, float, float]:
    """A motor packet's four outputs (0 = mincommand, 1 = +1000 µs), in Betaflight motor order."""
    if len(data) != MOTOR_PACKET.size:
        raise ValueError(f"a motor packet is {MOTOR_PACKET.size} bytes, got {len(data)}")
    raw = MOTOR_PACKET.unpack(data)
    return tuple(raw[i] for i in _PACKET_INDEX)  # type: ignore[return-value]


def motor_pwm(outputs: Sequence[float]) -> np.ndarray:
    """Motor outputs as PWM µs: mincommand + 1000 · output, clamped to [1000, 2000]."""
    return np.clip(MINCOMMAND_US + 1000.0 * np.asarray(outputs, dtype=float), 1000.0, 2000.0)


@dataclass
class PacketStats:
    """What crossed the link: FDM packets sent, motor packets received, answers that came late
    and answers that never came."""

    sent: int = 0
    received: int = 0
    late: int = 0  # answers that came after the next step was due (sim time slowed for them)
    lost: int = 0  # no answer within reply_timeout_s: that step flew on the previous motors
    rc_sent: int = 0
    behind_us: int = 0  # the most the bridge ever ran behind its real-time grid
    rebases: int = 0  # steps sent late, after which the grid moved (sim time slowed)
    reply_us: list[int] = field(default_factory=list)  # FDM → motor answer latency, µs

    def to_json(self) -> dict[str, int]:
        return {"sent": self.sent, "received": self.received, "late": self.late, "lost": self.lost}


class BetaflightBridge:
    """Serves one twin to Betaflight SITL in real time: `step(rc)` = one twin step, one FDM packet."""

    def __init__(self, twin, host: str = "127.0.0.1", speed: float = 1.0, rc_every: int = 1,
                 reply_timeout_s: float = 0.05, send_rotor_speed: bool = False,
                 fdm_port: int = FDM_PORT, rc_port: int = RC_PORT, motor_port: int = MOTOR_PORT) -> None:
        if not speed > 0.0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.twin = twin
        self.dt = float(twin.dt)
        self.speed = float(speed)
        self._wall_dt = self.dt / self.speed
        self.rc_every = max(1, int(rc_every))
        self.send_rotor_speed = send_rotor_speed
        self.reply_timeout_s = float(reply_timeout_s)
        self.stats = PacketStats()
        self._fdm_addr = (host, fdm_port)
        self._rc_addr = (host, rc_port)
        self._out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._motors = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._motors.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._motors.bind((host, motor_port))
        except OSError as exc:
            self.close()
            raise OSError(f"cannot listen for Betaflight's motor packets on UDP {host}:{motor_port}: "
                          f"{exc}") from exc
        self._motors.setblocking(False)
        self.outputs = (0.0, 0.0, 0.0, 0.0)
        self.pwm = motor_pwm(self.outputs)
        self.frame: SensorFrame = twin.reset()
        self._rotor_sampled_us: np.ndarray | None = None  # the sample times of the rotor speeds sent last
        self._gyro_sampled_us: int | None = None  # and of the gyro
        self.silent_steps = 0  # consecutive steps without an answer
        self._k = 0  # twin steps since the bridge started: the FDM clock, never reset
        self._t0 = time.perf_counter()

    def close(self) -> None:
        self._out.close()
        self._motors.close()

    def __enter__(self) -> BetaflightBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def sim_time_s(self) -> float:
        return self._k * self.dt

    def reset_twin(self, seed: int | None = None, state=None) -> SensorFrame:
        """Put the twin back at its initial state; the FDM clock keeps running (the SITL drops
        packets whose timestamp goes backwards)."""
        self.frame = self.twin.reset(seed, state)
        self._rotor_sampled_us = self._gyro_sampled_us = None  # the twin's clock starts again
        return self.frame

    def step(self, rc: Sequence[int],
             reply_timeout_s: float | None = None) -> tuple[SensorFrame, np.ndarray, bool]:
        """Send the current frame, wait (until the next step is due) for Betaflight's answer,
        step the twin with it. Returns (the frame sent, the PWM applied, whether it was fresh).
        `reply_timeout_s` overrides how long a late answer is waited for (the first step after
        a pause: the SITL's clock then runs at the pause's slow rate until the next packet)."""
        k = self._k
        due = self._t0 + k * self._wall_dt
        now = time.perf_counter()
        if now < due:
            # Slept, not spun: spinning would take a core from the SITL, whose answers then come
            # late more often (measured: more drift of its clock, not less).
            time.sleep(due - now)
        else:
            # Behind: never catch up. The SITL sets its clock rate from each pair of FDM packets
            # alone, so a burst would make its clock race and trip its RX failsafe; sim time
            # slows down instead.
            self.stats.behind_us = max(self.stats.behind_us, int((now - due) * 1e6))
            self.stats.rebases += 1
            self._t0 = now - k * self._wall_dt
        frame = self.frame
        t = k * self.dt
        truth = self.twin.truth()
        sent_at = time.perf_counter()
        rotor, gyro = None, frame.gyro
        if self.send_rotor_speed:
            rotor = telemetry_frames(frame, self._rotor_sampled_us)
            sampled = frame.rotor_speed_t_us
            self._rotor_sampled_us = None if sampled is None else np.array(sampled)
            gyro = gyro_sample(frame, self._gyro_sampled_us)
            self._gyro_sampled_us = frame.gyro_t_us
        self._out.sendto(pack_fdm(t, gyro, frame.accel, truth.attitude, truth.velocity,
                                  truth.position, rotor_speed=rotor), self._fdm_addr)
        self.stats.sent += 1
        if k % self.rc_every == 0:
            self._out.sendto(pack_rc(t, rc), self._rc_addr)
            self.stats.rc_sent += 1
        fresh = self._await_motors(self._t0 + (k + 1) * self._wall_dt, sent_at)
        if not fresh:
            # Late: real time says step now, but without Betaflight's answer the twin would fly
            # on stale motors. Wait a little longer (sim time slows down) rather than send the
            # next FDM packet: two packets queued at the SITL arrive back to back, and its clock
            # rate, taken from that one pair, would jump.
            self.stats.late += 1
            wait_s = self.reply_timeout_s if reply_timeout_s is None else reply_timeout_s
            fresh = self._await_motors(time.perf_counter() + wait_s, sent_at)
            if not fresh:
                self.stats.lost += 1
        self.silent_steps = 0 if fresh else self.silent_steps + 1
        pwm = self.pwm
        self.frame = self.twin.step(pwm)
        self._k = k + 1
        return frame, pwm, fresh

    def drain(self) -> int:
        """Drop motor packets waiting unread (an answer that came after its step gave up on it
        would otherwise be taken for the next step's, and every answer after it would be one
        step behind); returns how many."""
        dropped = 0
        while True:
            try:
                self._motors.recv(64)
            except BlockingIOError:
                return dropped
            dropped += 1

    def send_rc(self, rc: Sequence[int]) -> None:
        """An RC packet alone, between steps (the twin does not move)."""
        self._out.sendto(pack_rc(self._k * self.dt, rc), self._rc_addr)
        self.stats.rc_sent += 1

    def idle(self, rc: Sequence[int], seconds: float) -> None:
        """Keep the link alive (and the SITL's clock running) for `seconds` of twin time."""
        for _ in range(max(1, round(seconds / self.dt))):
            self.step(rc)

    def _await_motors(self, deadline: float, sent_at: float) -> bool:
        fresh = False
        sock = self._motors
        while True:
            try:
                data = sock.recv(64)
            except BlockingIOError:
                if fresh:
                    return True
                remaining = deadline - time.perf_counter()
                if remaining <= 0.0:
                    return False
                sock.settimeout(remaining)
                try:
                    data = sock.recv(64)
                except (TimeoutError, BlockingIOError):
                    return False
                finally:
                    sock.setblocking(False)
            if len(data) != MOTOR_PACKET.size:
                continue
            self.stats.received += 1
            if not fresh:
                self.stats.reply_us.append(int((time.perf_counter() - sent_at) * 1e6))
            self.outputs = unpack_motors(data)
            self.pwm = motor_pwm(self.outputs)
            fresh = True
