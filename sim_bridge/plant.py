"""The plant around the rigid body: motors and sensors, one model of each.

MuJoCo integrates the airframe under the rotors' thrust; everything between a PWM
command and that thrust (`MotorModel`) and the airframe's effects (`AirframeEffects`, the gyro's
and the ESC bus's delays among them) are here, pure numpy, no MuJoCo; the sensors' noise is
`sim_bridge.sensor_model`'s. The single twin
(`sim_bridge.twin`), the batched environment (`sim_bridge.vec_env`) and the Error bound
(`evaluation.bound`) all use these, so a new effect is written once, here.

Both models work on any batch shape: arrays (..., 4) of rotors, (..., 3) of axes; one
vehicle is shape (4,). The twin ticks one vehicle at 1 kHz, where numpy's per-call
overhead on a 4-vector costs more than the physics step, so `MotorModel.step_one` does
the same IEEE operations in the same order on plain floats; tests/sim_bridge/test_plant.py
holds the two paths to the last bit. A new motor effect goes into both, side by side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fcemu.sim_bridge.airframe import Airframe, MotorSpec


@dataclass(frozen=True)
class MotorModel:
    """Four rotors at time step `dt`: PWM → speed command → first-order lag → thrust.

    The command is linear in PWM between `pwm_min` (0 rad/s) and `pwm_max`
    (`max_rotor_speed`), clipped to that range. Each step closes the fraction α of the
    gap between command and speed, α = 1 − exp(−dt/τ) with τ_up spinning up and τ_down
    spinning down. Thrust is k_F·ω²; the yaw moment, k_M·thrust against the spin, is the
    MJCF actuator's gear (`sim_bridge.airframe.build_mjcf`).
    """

    pwm_min: float
    pwm_max: float
    max_rotor_speed: float  # rad/s at pwm_max
    speed_per_us: float  # rad/s of command per µs of PWM
    alpha_up: float | np.ndarray  # fraction of a rising speed gap closed per step (per vehicle (n, 1))
    alpha_down: float | np.ndarray  # fraction of a falling speed gap closed per step
    kf: float  # thrust = kf·ω², N/(rad/s)²
    km: float  # yaw moment = km·thrust, m
    dt: float

    @classmethod
    def from_spec(cls, spec: MotorSpec, dt: float) -> MotorModel:
        return cls(spec.pwm_min, spec.pwm_max, spec.max_rotor_speed,
                   spec.max_rotor_speed / (spec.pwm_max - spec.pwm_min),
                   float(1.0 - np.exp(-dt / spec.tau_up)), float(1.0 - np.exp(-dt / spec.tau_down)),
                   spec.kf, spec.km, dt)

    @property
    def max_thrust(self) -> float:
        return self.kf * self.max_rotor_speed**2

    def step(self, omega: np.ndarray, pwm: np.ndarray, kf: float | np.ndarray | None = None,
             speed_scale: float | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One step of rotor speeds `omega` (..., 4) under `pwm` (µs); returns (new ω, thrust in N).

        `kf` overrides the model's thrust coefficient, e.g. per vehicle (n, 1) in a batch
        of randomised airframes. `speed_scale` multiplies the speed command (battery sag,
        `Battery.speed_scale`; per vehicle (n, 1)).
        """
        error = np.clip(np.asarray(pwm, dtype=np.float64), self.pwm_min, self.pwm_max)
        error -= self.pwm_min
        error *= self.speed_per_us
        if speed_scale is not None:
            error *= speed_scale
        error -= omega
        gain = np.where(error > 0.0, self.alpha_up, self.alpha_down)
        gain *= error
        omega = omega + gain
        thrust = (self.kf if kf is None else kf) * omega
        thrust *= omega
        return omega, thrust

    def step_one(self, omega: list[float], pwm: list[float],
                 speed_scale: float | None = None) -> tuple[list[float], list[float]]:
        """`step` for one vehicle in plain floats: the same operations, a few µs instead of tens."""
        lo, hi, per_us, kf = self.pwm_min, self.pwm_max, self.speed_per_us, self.kf
        up, down = self.alpha_up, self.alpha_down
        speeds, thrust = [0.0] * 4, [0.0] * 4
        for i in range(4):
            v, w = pwm[i], omega[i]
            if speed_scale is None:
                error = ((lo if v < lo else hi if v > hi else v) - lo) * per_us - w
            else:
                error = ((lo if v < lo else hi if v > hi else v) - lo) * per_us * speed_scale - w
            w = w + (up if error > 0.0 else down) * error
            speeds[i] = w
            thrust[i] = kf * w * w
        return speeds, thrust

    def thrust_one(self, omega: list[float]) -> list[float]:
        kf = self.kf
        return [kf * w * w for w in omega]


def _rotor_sum(x: np.ndarray, spin: np.ndarray | None = None) -> np.ndarray:
    """Σ over the four rotors (last axis) in a fixed order, optionally signed by spin."""
    if spin is None:
        return (x[..., 0] + x[..., 1]) + (x[..., 2] + x[..., 3])
    return (spin[0] * x[..., 0] + spin[1] * x[..., 1]) + (spin[2] * x[..., 2] + spin[3] * x[..., 3])


def body_torque(rates: np.ndarray, omega: np.ndarray, omega_before: np.ndarray, damping: np.ndarray,
                rotor_inertia: float | np.ndarray, spin: np.ndarray, dt: float,
                com_offset: np.ndarray | None = None, thrust: np.ndarray | None = None) -> np.ndarray:
    """FRD torque (..., 3) on the body beside thrust and drag, from body `rates` (..., 3) FRD.

    Aerodynamic damping −D·Ω (`damping` (..., 3)). Rotor i (spin s_i, +1 counter-clockwise
    seen from above, i.e. about −z FRD) carries angular momentum −s_i·J_r·ω_i along z, so
    the rotors hold h = (0, 0, h_z), h_z = −J_r·Σ s_i ω_i. Speeding them up pushes the body
    the other way, −dh/dt = J_r·Σ s_i dω_i/dt about z (the sign of the drag torque
    k_M·s_i·T_i); a body turning at Ω with spinning rotors feels the gyroscopic moment
    −Ω × h = (−q·h_z, p·h_z, 0). `rotor_inertia` is a scalar or per vehicle (...,). A centre of
    mass `com_offset` (..., 3) FRD off the rotors' centre puts the rotors' total `thrust` (..., 4)
    N (along −z) off it: c × (0, 0, T) = (c_y·T, −c_x·T, 0).
    """
    p, q, r = rates[..., 0], rates[..., 1], rates[..., 2]
    h_z = -(rotor_inertia * _rotor_sum(omega, spin))
    spin_up = rotor_inertia * (_rotor_sum(omega - omega_before, spin) / dt)
    roll, pitch = -damping[..., 0] * p - q * h_z, -damping[..., 1] * q + p * h_z
    if com_offset is not None and thrust is not None:
        total = thrust.sum(axis=-1)
        roll, pitch = roll + com_offset[..., 1] * total, pitch - com_offset[..., 0] * total
    return np.stack([roll, pitch, -damping[..., 2] * r + spin_up], axis=-1)


def body_torque_one(rates: list[float], omega: list[float], before: list[float], damping: list[float],
                    rotor_inertia: float, spin: list[float], dt: float, com_offset: list[float] | None = None,
                    thrust: list[float] | None = None) -> list[float]:
    """`body_torque` for one vehicle in plain floats: the same operations in the same order."""
    s0, s1, s2, s3 = spin
    w0, w1, w2, w3 = omega
    b0, b1, b2, b3 = before
    p, q, r = rates
    h_z = -(rotor_inertia * ((s0 * w0 + s1 * w1) + (s2 * w2 + s3 * w3)))
    spin_up = rotor_inertia * (((s0 * (w0 - b0) + s1 * (w1 - b1)) + (s2 * (w2 - b2) + s3 * (w3 - b3))) / dt)
    roll, pitch = -damping[0] * p - q * h_z, -damping[1] * q + p * h_z
    if com_offset is not None and thrust is not None:
        total = sum(thrust)
        roll, pitch = roll + com_offset[1] * total, pitch - com_offset[0] * total
    return [roll, pitch, -damping[2] * r + spin_up]


@dataclass(frozen=True)
class Battery:
    """A battery that sags with the charge drawn and the load; the rotors' top speed follows it.

    Voltage V = V_full − k·Q − R·I, with Q the charge drawn so far (A·s) and I the current,
    I = c·Σ T_i^1.5 (ideal induced power of a hovering rotor, momentum theory, over a
    constant voltage × efficiency folded into c). The speed command of the ESCs scales
    with V / V_full (`MotorModel.step(speed_scale=...)`); the current of a step drives the
    next one's sag. Parameters are scalars or per vehicle (n, 1).
    """

    voltage_full: float | np.ndarray
    sag_per_charge: float | np.ndarray  # V / (A·s)
    resistance: float | np.ndarray  # Ω
    current_per_thrust: float | np.ndarray  # A / N^1.5
    dt: float

    def speed_scale(self, charge: np.ndarray, current: np.ndarray) -> np.ndarray:
        volts = self.voltage_full - self.sag_per_charge * charge - self.resistance * current
        return np.maximum(volts / self.voltage_full, 0.0)

    def current(self, thrust: np.ndarray) -> np.ndarray:
        """Current (..., 1) drawn by rotors making `thrust` (..., 4) N."""
        t = np.maximum(thrust, 0.0)
        return self.current_per_thrust * _rotor_sum(t * np.sqrt(t))[..., None]


def gyro_vibration(amplitude: np.ndarray, omega: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """The rotors' vibration in the gyro (..., 3): amplitude_axis · Σ_i ω_i² sin φ_i.

    Each rotor shakes the frame once per revolution (imbalance: force ∝ ω²); `phase` is the
    rotor's angle (..., 4), advanced by ω·dt each step (`advance_phase`).
    """
    shake = _rotor_sum(omega * omega * np.sin(phase))
    return amplitude * shake[..., None]


def advance_phase(phase: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    return np.remainder(phase + omega * dt, 2.0 * np.pi)


class DelayLine:
    """A ring buffer: what goes in comes out `delay` pushes later (0: at once), per row of a batch.

    `capacity` bounds the delays (set_delay) it can hold; rows of a batch may differ.
    """

    def __init__(self, delay: int | np.ndarray, shape: tuple[int, ...], capacity: int | None = None) -> None:
        self.delay = np.asarray(delay, dtype=np.int64)
        self._size = int(capacity if capacity is not None else self.delay.max()) + 1
        if self.delay.max() >= self._size or self.delay.min() < 0:
            raise ValueError(f"delays {self.delay} outside 0..{self._size - 1} ticks")
        self._buf = np.zeros((self._size, *shape))
        self._pos = 0
        self._rows = np.arange(shape[0]) if self.delay.ndim else None

    def fill(self, value: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Start over holding `value` (of `rows`, an index array, in a batch); returns it."""
        if rows is None:
            self._buf[:] = value
        else:
            self._buf[:, rows] = value
        return value

    def set_delay(self, rows: np.ndarray, delay: int) -> None:
        if not 0 <= delay < self._size:
            raise ValueError(f"delay {delay} outside 0..{self._size - 1} ticks")
        self.delay[rows] = delay

    def push(self, value: np.ndarray) -> np.ndarray:
        pos = self._pos
        self._buf[pos] = value
        self._pos = (pos + 1) % self._size
        if self._rows is None:
            return self._buf[(pos - int(self.delay)) % self._size].copy()
        return self._buf[(pos - self.delay) % self._size, self._rows]


class AirframeEffects:
    """The airframe's effects beside the rigid body and the motor lag, with their state.

    One vehicle (batch shape ()) or a batch (n,), each row with its own parameters
    (`set_row`, e.g. a randomised airframe). Per physics step, in this order: the PWM
    through the ESC delay (`command`); the battery's speed scale for the motor step
    (`speed_scale`); the body torque for MuJoCo (`torque`, FRD); after the step, the
    battery's load and the rotor angles (`advance`); the gyro reading with the rotors'
    vibration, then the sensor model's noise, through the gyro delay (`gyro_*`). An
    effect no row has costs nothing.
    """

    def __init__(self, airframe: Airframe, dt: float, batch_shape: tuple[int, ...] = (),
                 delay_capacity: int | None = None) -> None:
        self.dt, self.shape = dt, batch_shape
        self.spin = airframe.spin.astype(float)
        self.damping = np.zeros((*batch_shape, 3))
        self.com_offset = np.zeros((*batch_shape, 3))
        self.rotor_inertia = np.zeros(batch_shape)
        self.vibration = np.zeros((*batch_shape, 3))
        self.battery_params = np.zeros((4, *batch_shape, 1))  # V_full, k, R, c
        self.charge = np.zeros((*batch_shape, 1))
        self.charge_at_start = np.zeros((*batch_shape, 1))
        self.current = np.zeros((*batch_shape, 1))
        self.phase = np.zeros((*batch_shape, 4))
        self.battery = Battery(*self.battery_params, dt)  # views: set_row writes through
        self.torques = self.sags = self.shakes = False
        esc, gyro = airframe.esc_delay_ticks, airframe.gyro_delay_ticks
        self.esc = DelayLine(np.full(batch_shape, esc), (*batch_shape, 4), delay_capacity or esc)
        self.gyro_line = DelayLine(np.full(batch_shape, gyro), (*batch_shape, 3), delay_capacity or gyro)
        self.esc_delays, self.gyro_delays = bool(esc), bool(gyro)
        late = airframe.esc_telemetry_delay_ticks
        self.telemetry_line = DelayLine(np.full(batch_shape, late), (*batch_shape, 4), delay_capacity or late)
        self.telemetry_delays, self.loses = bool(late), False
        self.loss = np.zeros((*batch_shape, 1))  # each motor's frame lost with this probability a step
        self.delivered = np.zeros((*batch_shape, 4))  # the rotor speeds last delivered, held when lost
        self.age = np.zeros((*batch_shape, 4), dtype=np.int64)  # their ages, ticks
        self.set_row(None, airframe)

    def set_row(self, row: int | None, airframe: Airframe) -> None:
        """Take `airframe`'s parameters for one row of the batch (None: all rows)."""
        at = ... if row is None else row
        self.damping[at] = airframe.rate_damping
        self.com_offset[at] = airframe.centre_of_mass_offset
        self.rotor_inertia[at] = airframe.rotor_inertia
        self.vibration[at] = airframe.gyro_vibration
        battery = (airframe.battery_voltage_full, airframe.battery_sag_per_charge,
                   airframe.battery_resistance, airframe.battery_current_per_thrust)
        for params, value in zip(self.battery_params, battery, strict=True):
            params[at] = value
        self.charge_at_start[at] = airframe.battery_drawn_at_start
        self.loss[at] = airframe.esc_telemetry_loss
        self.loses |= bool(airframe.esc_telemetry_loss)
        self.torques |= airframe.body_torques
        self.sags |= airframe.battery_sags
        self.shakes |= any(airframe.gyro_vibration)
        if row is not None:
            self.esc.set_delay(row, airframe.esc_delay_ticks)
            self.gyro_line.set_delay(row, airframe.gyro_delay_ticks)
            self.telemetry_line.set_delay(row, airframe.esc_telemetry_delay_ticks)
            self.telemetry_delays |= bool(airframe.esc_telemetry_delay_ticks)
            self.esc_delays |= bool(airframe.esc_delay_ticks)
            self.gyro_delays |= bool(airframe.gyro_delay_ticks)
        if not self.shape:
            # The one-vehicle path's parameters as plain floats, taken here rather than per step.
            self._damping_one, self._inertia_one = self.damping.tolist(), float(self.rotor_inertia)
            self._com_one = self.com_offset.tolist() if any(airframe.centre_of_mass_offset) else None
            self._spin_one = self.spin.tolist()
            self._battery_one = tuple(float(p[0]) for p in self.battery_params)

    def reset(self, pwm: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Battery as charged at the start, rotors at angle 0, the ESC line holding `pwm` (of `rows`)."""
        at = ... if rows is None else rows
        self.charge[at] = self.charge_at_start[at]
        self.current[at] = 0.0
        self.phase[at] = 0.0
        if self.esc_delays:
            self.esc.fill(pwm, rows)

    def command(self, pwm: np.ndarray) -> np.ndarray:
        return self.esc.push(pwm) if self.esc_delays else pwm

    def speed_scale(self) -> np.ndarray | None:
        return self.battery.speed_scale(self.charge, self.current) if self.sags else None

    def torque(self, rates: np.ndarray, omega: np.ndarray, omega_before: np.ndarray,
               thrust: np.ndarray | None = None) -> np.ndarray:
        return body_torque(rates, omega, omega_before, self.damping, self.rotor_inertia, self.spin, self.dt,
                           self.com_offset, thrust)

    def advance(self, omega: np.ndarray, thrust: np.ndarray) -> None:
        if self.sags:
            self.current = self.battery.current(thrust)
            self.charge = self.charge + self.current * self.dt
        if self.shakes:
            self.phase = advance_phase(self.phase, omega, self.dt)

    # One vehicle (batch shape ()) in plain floats, the batch path's operations in its order:
    # numpy's per-call overhead on 4-vectors would dominate the twin's 1 kHz step.
    def speed_scale_one(self) -> float | None:
        if not self.sags:
            return None
        v, k, r, _ = self._battery_one
        volts = v - k * float(self.charge[0]) - r * float(self.current[0])
        scale = volts / v
        return scale if scale > 0.0 else 0.0

    def torque_one(self, rates: list[float], omega: list[float], before: list[float],
                   thrust: list[float] | None = None) -> list[float]:
        return body_torque_one(rates, omega, before, self._damping_one, self._inertia_one, self._spin_one,
                               self.dt, self._com_one, thrust)

    def advance_one(self, omega: list[float], thrust: list[float]) -> None:
        if self.sags:
            t = [x if x > 0.0 else 0.0 for x in thrust]
            c = self._battery_one[3]
            current = c * ((t[0] * math.sqrt(t[0]) + t[1] * math.sqrt(t[1]))
                           + (t[2] * math.sqrt(t[2]) + t[3] * math.sqrt(t[3])))
            self.current[0] = current
            self.charge[0] = float(self.charge[0]) + current * self.dt
        if self.shakes:
            self.phase = advance_phase(self.phase, np.array(omega), self.dt)

    @property
    def gyro_effects(self) -> bool:
        return self.shakes or self.gyro_delays

    def gyro_truth(self, rates: np.ndarray, omega: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """What the gyro senses before its noise: the rates plus the rotors' vibration."""
        if not self.shakes:
            return rates
        at = ... if rows is None else rows
        return rates + gyro_vibration(self.vibration[at], omega, self.phase[at])

    def gyro_delayed(self, reading: np.ndarray, rows: np.ndarray | None = None,
                     reset: bool = False) -> np.ndarray:
        """The reading through the gyro pipeline's delay; `reset`: the line starts over holding it."""
        if not self.gyro_delays:
            return reading
        return self.gyro_line.fill(reading, rows) if reset else self.gyro_line.push(reading)

    @property
    def telemetry_effects(self) -> bool:
        return self.telemetry_delays or self.loses

    def telemetry(self, reading: np.ndarray, lost_draw: np.ndarray | None, rows: np.ndarray | None = None,
                  reset: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The rotor speeds the ESCs deliver of `reading` (of `rows`), and each one's age in ticks.

        Through the bus's delay; then each motor's frame is lost where its uniform draw
        (`lost_draw`, one per motor) falls below the loss, and the last one delivered stands,
        growing older. `reset`: the bus starts over delivering `reading`, nothing lost.
        """
        at = ... if rows is None else rows
        if self.telemetry_delays:
            reading = self.telemetry_line.fill(reading, rows) if reset else self.telemetry_line.push(reading)
        fresh = np.broadcast_to(self.telemetry_line.delay[at][..., None], reading.shape)
        if self.loses and not reset and lost_draw is not None:
            lost = lost_draw < self.loss[at]
            reading = np.where(lost, self.delivered[at], reading)
            self.age[at] = np.where(lost, self.age[at] + 1, fresh)
        else:
            self.age[at] = fresh
        self.delivered[at] = reading
        return reading, self.age[at]
