"""The plant around the rigid body: motors and sensors, one model of each.

MuJoCo integrates the airframe under the rotors' thrust; everything between a PWM
command and that thrust (`MotorModel`) and between the true motion and what the flight
controller reads (`SensorModel`) is here, pure numpy, no MuJoCo. The single twin
(`sim_bridge.twin`), the batched environment (`sim_bridge.vec_env`) and the Error bound
(`evaluation.bound`) all use these, so a new effect is written once, here.

Both models work on any batch shape: arrays (..., 4) of rotors, (..., 3) of axes; one
vehicle is shape (4,). The twin ticks one vehicle at 1 kHz, where numpy's per-call
overhead on a 4-vector costs more than the physics step, so `MotorModel.step_one` does
the same IEEE operations in the same order on plain floats; tests/sim_bridge/test_plant.py
holds the two paths to the last bit. A new motor effect goes into both, side by side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_bridge.airframe import MotorSpec


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
    alpha_up: float  # fraction of a rising speed gap closed per step
    alpha_down: float  # fraction of a falling speed gap closed per step
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

    def step(self, omega: np.ndarray, pwm: np.ndarray,
             kf: float | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One step of rotor speeds `omega` (..., 4) under `pwm` (µs); returns (new ω, thrust in N).

        `kf` overrides the model's thrust coefficient, e.g. per vehicle (n, 1) in a batch
        of randomised airframes.
        """
        error = np.clip(np.asarray(pwm, dtype=np.float64), self.pwm_min, self.pwm_max)
        error -= self.pwm_min
        error *= self.speed_per_us
        error -= omega
        gain = np.where(error > 0.0, self.alpha_up, self.alpha_down)
        gain *= error
        omega = omega + gain
        thrust = (self.kf if kf is None else kf) * omega
        thrust *= omega
        return omega, thrust

    def step_one(self, omega: list[float], pwm: list[float]) -> tuple[list[float], list[float]]:
        """`step` for one vehicle in plain floats: the same operations, a few µs instead of tens."""
        lo, hi, per_us, kf = self.pwm_min, self.pwm_max, self.speed_per_us, self.kf
        up, down = self.alpha_up, self.alpha_down
        speeds, thrust = [0.0] * 4, [0.0] * 4
        for i in range(4):
            v, w = pwm[i], omega[i]
            error = ((lo if v < lo else hi if v > hi else v) - lo) * per_us - w
            w = w + (up if error > 0.0 else down) * error
            speeds[i] = w
            thrust[i] = kf * w * w
        return speeds, thrust

    def thrust_one(self, omega: list[float]) -> list[float]:
        kf = self.kf
        return [kf * w * w for w in omega]


@dataclass(frozen=True)
class SensorNoise:
    """Sensor imperfections; all zero by default, as in the paper's twin."""

    gyro_std: float = 0.0  # rad/s, white noise per sample
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s, FRD
    accel_std: float = 0.0  # m/s^2
    accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotor_speed_std: float = 0.0  # rad/s

    @property
    def enabled(self) -> bool:
        return bool(self.gyro_std or self.accel_std or self.rotor_speed_std
                    or any(self.gyro_bias) or any(self.accel_bias))


class SensorModel:
    """What the gyro, accelerometer and ESC telemetry report: truth + bias + white noise, FRD.

    The noise of one frame is `DRAWS` standard normal draws in a fixed order (gyro 3,
    accelerometer 3, rotor speed 4): a vehicle drawing each frame's on its own and a
    batch drawing many frames ahead (`NoiseStreams`) read the same numbers.
    """

    DRAWS = 10

    def __init__(self, noise: SensorNoise | None = None) -> None:
        self.noise = noise or SensorNoise()
        self.enabled = self.noise.enabled
        self._gyro_bias = np.asarray(self.noise.gyro_bias, dtype=np.float64)
        self._accel_bias = np.asarray(self.noise.accel_bias, dtype=np.float64)

    def read(self, gyro: np.ndarray, accel: np.ndarray | None, rotor_speed: np.ndarray,
             z: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Readings of the true rates (..., 3), specific force (None: not wanted), rotor speeds (..., 4)."""
        n = self.noise
        gyro = gyro + (self._gyro_bias + n.gyro_std * z[..., 0:3])
        if accel is not None:
            accel = accel + (self._accel_bias + n.accel_std * z[..., 3:6])
        rotor_speed = rotor_speed + n.rotor_speed_std * z[..., 6:10]
        return gyro, accel, rotor_speed


class NoiseStreams:
    """One seeded standard-normal stream per vehicle of a batch, `width` draws per frame.

    Draws `block` frames at a time per vehicle: the same numbers, in the same order, as a
    generator drawing each frame when it is needed (numpy fills arrays draw by draw).
    """

    def __init__(self, n: int, width: int = SensorModel.DRAWS, block: int = 256) -> None:
        self.block = block
        self._rngs = [np.random.default_rng() for _ in range(n)]
        self._draws = np.zeros((n, block, width))
        self._pos = np.zeros(n, dtype=np.int64)

    def reseed(self, i: int, seed: int | None) -> None:
        self._rngs[i] = np.random.default_rng(seed)
        self._rngs[i].standard_normal(out=self._draws[i])
        self._pos[i] = 0

    def next(self, idx: np.ndarray) -> np.ndarray:
        """The next frame's draws of vehicles `idx`, (len(idx), width)."""
        pos = self._pos[idx]
        z = self._draws[idx, pos]
        pos += 1
        self._pos[idx] = pos
        for i in idx[pos == self.block]:
            self._rngs[i].standard_normal(out=self._draws[i])
            self._pos[i] = 0
        return z
