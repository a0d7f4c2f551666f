"""Attitude estimation from the firmware's own gyro and accelerometer (Mahony filter).

The attitude quaternion (w, x, y, z) rotates FRD body vectors into NED. The accelerometer
measures specific force (level at rest: [0, 0, -g]); its direction corrects roll and pitch,
and the gyro bias is estimated by the integral term. Yaw is the gyro's integral: there is
no magnetometer. Plain floats throughout: `update` runs every loop tick and costs a few µs.

A vertical velocity estimate rides along (NED z, down positive): the accelerometer rotated
into NED plus gravity, integrated, with a slow leak so that a bias cannot run it away. It
starts at zero on the ground and is what the failsafe descent controls on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

GRAVITY = 9.81


@dataclass(frozen=True)
class EstimatorGains:
    kp: float = 1.0  # accel correction, rad/s per unit of direction error
    ki: float = 0.05  # gyro-bias learning
    accel_gate: float = 0.15  # skip correction when | |a|/g - 1 | exceeds this (manoeuvres)
    vz_leak_s: float = 30.0  # time constant pulling the vertical speed estimate to zero


class AttitudeEstimator:
    __slots__ = ("_bias", "_gains", "_gate", "_ki", "_kp", "_leak", "q", "vz")

    def __init__(self, gains: EstimatorGains | None = None) -> None:
        g = self._gains = gains or EstimatorGains()
        # Plain floats in slots: `update` reads them every tick.
        self._kp, self._ki, self._gate, self._leak = g.kp, g.ki, g.accel_gate, 1.0 / g.vz_leak_s
        self.reset()

    def reset(self, q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)) -> None:
        self.q = tuple(q)
        self._bias = (0.0, 0.0, 0.0)
        self.vz = 0.0

    def level_from_accel(self, ax: float, ay: float, az: float) -> None:
        """Start at the roll and pitch the accelerometer shows (vehicle at rest), yaw 0."""
        roll = math.atan2(-ay, -az)
        pitch = math.atan2(ax, math.hypot(ay, az))
        self.reset(quat_from_euler(roll, pitch, 0.0))

    def update(self, gx: float, gy: float, gz: float, ax: float, ay: float, az: float, dt: float) -> None:
        w, x, y, z = self.q
        bx, by, bz = self._bias
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        if norm > 1e-6 and abs(norm / GRAVITY - 1.0) < self._gate:
            # Expected specific-force direction in body axes: -(R^T · [0, 0, 1]) (up, in FRD).
            vx = -2.0 * (x * z - w * y)
            vy = -2.0 * (y * z + w * x)
            vz = -(w * w - x * x - y * y + z * z)
            inv = 1.0 / norm
            mx, my, mz = ax * inv, ay * inv, az * inv
            ex, ey, ez = my * vz - mz * vy, mz * vx - mx * vz, mx * vy - my * vx
            ki_dt, kp = self._ki * dt, self._kp
            bx, by, bz = bx + ki_dt * ex, by + ki_dt * ey, bz + ki_dt * ez
            self._bias = (bx, by, bz)
            gx += kp * ex + bx
            gy += kp * ey + by
            gz += kp * ez + bz
        else:
            gx, gy, gz = gx + bx, gy + by, gz + bz
        h = 0.5 * dt
        w, x, y, z = (w - h * (x * gx + y * gy + z * gz), x + h * (w * gx + y * gz - z * gy),
                      y + h * (w * gy - x * gz + z * gx), z + h * (w * gz + x * gy - y * gx))
        n = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w * n, x * n, y * n, z * n
        self.q = (w, x, y, z)
        # Down component of the specific force in NED, plus gravity: vertical acceleration.
        a_down = (2.0 * (x * z - w * y) * ax + 2.0 * (y * z + w * x) * ay
                  + (w * w - x * x - y * y + z * z) * az) + GRAVITY
        self.vz += (a_down - self.vz * self._leak) * dt

    def euler(self) -> tuple[float, float, float]:
        return euler_from_quat(self.q)

    def tilt_cos(self) -> float:
        """cos of the angle between body z and the vertical (1 when level, < 0 inverted)."""
        w, x, y, z = self.q
        return w * w - x * x - y * y + z * z


def quat_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def euler_from_quat(q) -> tuple[float, float, float]:
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw
