"""The digital twin: MuJoCo Iris, per-rotor motor model, sensors in FRD.

`Twin.step(pwm)` advances exactly one physics step (1 ms by default) and returns the
`SensorFrame` the flight controller would read next. The motors and sensors are
`sim_bridge.plant`'s models; MuJoCo integrates the rigid body under the rotors' thrust and
the airframe's other torques (`AirframeEffects`: damping, spin-up reaction, gyroscopic
moment, applied as generalised forces on the body's rotational joint). Everything random
(sensor noise, initial state) draws from the generator seeded by `reset(seed)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.airframe import FLU_FROM_FRD, Airframe, build_mjcf, load_airframe
from fcemu.sim_bridge.faults import FaultInjector
from fcemu.sim_bridge.plant import AirframeEffects, MotorModel
from fcemu.sim_bridge.sensor_model import SensorModel, SensorNoise


@dataclass(frozen=True)
class TwinState:
    """A full initial state. Quaternion (w, x, y, z) rotates FRD body into NED."""

    attitude: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    body_rates: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s FRD
    rotor_speed: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # rad/s
    position: tuple[float, float, float] | None = None  # NED m; free rig only, None = on ground
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # NED m/s; free rig only


def hover_state(airframe: Airframe, throttle: float) -> TwinState:
    """Level, rates zero, every rotor at the speed `throttle` commands with zero demands: in flight."""
    m = airframe.motor
    pwm = min(max(PWM_MIN + PWM_SPAN * throttle, m.pwm_min), m.pwm_max)
    speed = (pwm - m.pwm_min) * m.max_rotor_speed / (m.pwm_max - m.pwm_min)
    return TwinState(rotor_speed=(speed,) * 4)


@dataclass(frozen=True)
class Truth:
    """Ground truth, for telemetry and tests only; the controller never sees it."""

    position: np.ndarray  # NED m (zeros in the ball-joint rig)
    velocity: np.ndarray  # NED m/s
    attitude: np.ndarray  # quaternion (w, x, y, z), FRD -> NED
    body_rates: np.ndarray  # FRD rad/s
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))  # NED m/s^2


def _ned_quat_from_mujoco(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], q[1], -q[2], -q[3]])


class Twin:
    """One Iris in one rig, stepped in lockstep with the flight controller."""

    def __init__(
        self,
        airframe: Airframe | str = "iris",
        rig: str = "rig",
        noise: SensorNoise | None = None,
        dt: float = 0.001,
    ) -> None:
        self.airframe = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)
        self.rig = rig
        if noise is None and self.airframe.gyro_noise_std:
            noise = SensorNoise(gyro_std=self.airframe.gyro_noise_std)
        self.sensors = SensorModel(noise)
        self.noise = self.sensors.noise
        self.dt = dt
        self.dt_us = round(dt * 1e6)
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(self.airframe, rig, dt))
        self.data = mujoco.MjData(self.model)
        self.motors = MotorModel.from_spec(self.airframe.motor, dt)
        gyro, accel = self.model.sensor("gyro").adr[0], self.model.sensor("accel").adr[0]
        if accel != gyro + 3:
            raise RuntimeError("the MJCF must declare the accelerometer right after the gyro")
        self._imu = slice(gyro, gyro + 6)
        self._sensordata = self.data.sensordata
        self._ctrl = self.data.ctrl
        self._imu_sign = np.tile(FLU_FROM_FRD, 2)
        self._noisy = self.sensors.enabled
        self.effects = AirframeEffects(self.airframe, dt)
        self._rot = slice(0, 3) if rig == "rig" else slice(3, 6)
        self._plain = not (self.effects.torques or self.effects.sags or self.effects.esc_delays
                           or self.effects.shakes)
        self._omega = [0.0] * 4
        # the gyro and rotor speed readings as sampled, before the gyro's delay and the ESC bus
        self.sampled: tuple[np.ndarray, np.ndarray] = (np.zeros(3), np.zeros(4))
        self._t_us = 0
        self._rng = np.random.default_rng()
        self._telemetry_rng = np.random.default_rng()  # which ESC frames the bus loses
        self.faults: FaultInjector | None = None  # injected faults (sim_bridge/faults.py); None: none
        self._base = self.model.body("base").id
        self._base_mass = float(self.model.body_mass[self._base])
        self._base_inertia = self.model.body_inertia[self._base].copy()
        self._payload: float | None = None  # the load the base carries now, × the airframe's mass
        self.reset()

    @property
    def t_us(self) -> int:
        return self._t_us

    @property
    def rotor_speed(self) -> np.ndarray:
        return np.array(self._omega)

    def reset(self, seed: int | None = None, state: TwinState | None = None,
              telemetry_seed: int | None = None) -> SensorFrame:
        """Start over at t = 0 from `state` (at rest, level, by default); returns the first frame.

        `seed` seeds the sensor noise, `telemetry_seed` the ESC frames the bus loses (by
        default drawn from `seed`'s generator, when the airframe loses any)."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        if telemetry_seed is None and seed is not None and self.effects.loses:
            telemetry_seed = int(np.random.default_rng([seed, 1]).integers(2**63))
        if telemetry_seed is not None:
            self._telemetry_rng = np.random.default_rng(telemetry_seed)
        state = state or TwinState()
        if self._payload is not None:
            self._carry(None)
        mujoco.mj_resetData(self.model, self.data)
        quat = np.asarray(state.attitude, dtype=float)
        norm = np.linalg.norm(quat)
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"initial attitude {state.attitude} is not a rotation quaternion")
        quat = _ned_quat_from_mujoco(quat / norm)  # the conversion is its own inverse
        rates = np.asarray(state.body_rates, dtype=float) * FLU_FROM_FRD
        if self.rig == "rig":
            self.data.qpos[0:4] = quat
            self.data.qvel[0:3] = rates
        else:
            if state.position is not None:
                self.data.qpos[0:3] = np.asarray(state.position, dtype=float) * FLU_FROM_FRD
            self.data.qpos[3:7] = quat
            self.data.qvel[0:3] = np.asarray(state.velocity, dtype=float) * FLU_FROM_FRD
            self.data.qvel[3:6] = rates
        self._omega = [float(w) for w in state.rotor_speed]
        self.data.ctrl[:] = self.motors.thrust_one(self._omega)
        mujoco.mj_forward(self.model, self.data)
        self._t_us = 0
        self.effects.reset(np.asarray(self.airframe.motor.pwm_for_rotor_speed(np.array(self._omega))))
        return self._frame(reset=True)

    def step(self, pwm: np.ndarray) -> SensorFrame:
        """Apply PWM (µs, Betaflight motor order) for one step; return the next sensor frame."""
        # Four rotors in plain floats: numpy's per-call overhead would triple the step time.
        try:
            values = pwm.tolist() if isinstance(pwm, np.ndarray) else [float(v) for v in pwm]
        except TypeError:
            values = []
        if len(values) != 4 or not all(isinstance(v, (float, int)) and math.isfinite(v) for v in values):
            raise ValueError(f"pwm must be 4 finite values in µs, got {pwm!r}")
        faults = self.faults
        if faults is not None:
            values = faults.motor_command(values, self.motors.pwm_min)
        payload = None if faults is None else faults.payload
        if payload != self._payload:
            self._carry(payload)
        if self._plain:
            scale = None if faults is None else faults.speed_scale
            self._omega, thrust = self.motors.step_one(self._omega, values, scale)
            self._ctrl[:] = thrust if faults is None else faults.thrust(thrust)
        else:
            self._step_effects(values)
        mujoco.mj_step(self.model, self.data)
        if not self._plain:
            self.effects.advance_one(self._omega, self._ctrl.tolist())
        self._t_us += self.dt_us
        return self._frame()

    def _carry(self, payload: float | None) -> None:
        """Load the base with `payload` × the airframe's mass, spread as the airframe's own mass is
        (every moment of inertia grows by that share), or unload it (None)."""
        share = payload or 0.0
        self.model.body_mass[self._base] = self._base_mass + share * self.airframe.mass
        self.model.body_inertia[self._base] = self._base_inertia + share * self.airframe.inertia()
        self._payload = payload

    def _step_effects(self, pwm: list[float]) -> None:
        fx = self.effects
        pwm = fx.command(np.array(pwm)).tolist()
        before = self._omega
        scale, faults = fx.speed_scale_one(), self.faults
        if faults is not None and faults.speed_scale is not None:
            scale = faults.speed_scale * (1.0 if scale is None else scale)
        self._omega, thrust = self.motors.step_one(before, pwm, scale)
        self._ctrl[:] = thrust if faults is None else faults.thrust(thrust)
        if fx.torques:
            rates = (self.data.qvel[self._rot] * FLU_FROM_FRD).tolist()
            torque = fx.torque_one(rates, self._omega, before, self._ctrl.tolist())
            self.data.qfrc_applied[self._rot] = np.array(torque) * FLU_FROM_FRD

    def _frame(self, reset: bool = False) -> SensorFrame:
        imu = self._sensordata[self._imu] * self._imu_sign
        gyro, accel = imu[0:3], imu[3:6]
        omega = np.array(self._omega)
        fx = self.effects
        if fx.shakes:
            gyro = fx.gyro_truth(gyro, omega)
        if self._noisy:
            gyro, accel, omega = self.sensors.read(gyro, accel, omega,
                                                   self._rng.standard_normal(SensorModel.DRAWS))
        self.sampled = (gyro, omega)
        if fx.gyro_delays:
            gyro = fx.gyro_delayed(gyro, reset=reset)
        rotor_t_us = None
        if fx.telemetry_effects:
            lost_draw = None if reset or not fx.loses else self._telemetry_rng.random(4)
            omega, age = fx.telemetry(omega, lost_draw, reset=reset)
            rotor_t_us = self._t_us - age * self.dt_us
        if self.faults is not None:
            gyro, omega, gyro_t_us, fault_t_us = self.faults.read(gyro, omega, self._t_us)
            if rotor_t_us is not None:  # the fault acts on what the bus delivered, already this old
                fault_t_us = rotor_t_us if fault_t_us is None else fault_t_us - (self._t_us - rotor_t_us)
            return SensorFrame(self._t_us, gyro, accel, omega, gyro_t_us, fault_t_us)
        return SensorFrame(self._t_us, gyro, accel, omega, None, rotor_t_us)

    def clean_gyro(self) -> np.ndarray:
        """The gyro's reading now without vibration, noise or delay: the body rate the metrics
        score (what the vehicle did, not what its sensor said); never the controller's input."""
        return self._sensordata[self._imu][0:3] * FLU_FROM_FRD

    def truth(self) -> Truth:
        d = self.data
        if self.rig == "rig":
            quat, pos, vel = d.qpos[0:4], np.zeros(3), np.zeros(3)
            rates = d.qvel[0:3] * FLU_FROM_FRD
            acc = np.zeros(3)
        else:
            quat = d.qpos[3:7]
            pos = d.qpos[0:3] * FLU_FROM_FRD
            vel = d.qvel[0:3] * FLU_FROM_FRD
            rates = d.qvel[3:6] * FLU_FROM_FRD
            acc = d.qacc[0:3] * FLU_FROM_FRD
        return Truth(pos, vel, _ned_quat_from_mujoco(np.asarray(quat)), rates, acc)
