"""What the gyro reads beside the rate: the rotors' vibration and white noise.

The twin's vibration (`sim_bridge.plant.gyro_vibration`) is a_axis·Σ_i ω_i²·sin φ_i, φ_i the
rotor's angle. With ESC rpm the angles are the rotor speeds integrated, up to each rotor's
unknown starting angle, so the vibration is linear in ω_i²·sin φ_i and ω_i²·cos φ_i: fitted to
the gyro above the rates' band (the complement of `identify.smooth`), each rotor's amplitude is
the length of its two coefficients and a_axis their mean. The noise is then the level of what
is left, from its spectrum above the rotors' frequencies where the band is free of them.
Without rpm the vibration's amplitude comes from its power (`vibration_from_power`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import welch

from fcemu.evaluation.identify import MAX_DELAY_TICKS, SMOOTH_HZ, Estimate, smooth
from fcemu.evaluation.identify_log import FlightLog

NOISE_BAND_HZ = (250.0, 450.0)  # above an Iris-sized rotor's frequency, below Nyquist at 1 kHz


@dataclass(frozen=True)
class GyroFit:
    vibration: tuple[Estimate, Estimate, Estimate]  # rad/s per (rad/s)², per axis
    noise_std: float  # rad/s
    noise_how: str
    from_angles: bool  # the vibration fitted against the rotor angles (else from its power)


def _high(x: np.ndarray, dt: float) -> np.ndarray:
    return x - smooth(x, dt)


def fit_vibration(log: FlightLog) -> tuple[tuple[Estimate, Estimate, Estimate], np.ndarray] | None:
    """Per axis the amplitude and (T, 3) the fitted vibration; None without rpm."""
    if log.rotor_speed is None:
        return None
    dt, w = log.dt, log.rotor_speed
    angle = np.cumsum(w, axis=0) * dt
    columns = _high(np.concatenate([w**2 * np.sin(angle), w**2 * np.cos(angle)], axis=1), dt)
    y = _high(log.gyro, dt)
    best = None
    for shift in range(MAX_DELAY_TICKS + 1):
        n = len(y) - shift
        beta, *_ = np.linalg.lstsq(columns[:n], y[shift:], rcond=None)
        residual = y[shift:] - columns[:n] @ beta
        score = float(np.sum(residual**2))
        if best is None or score < best[0]:
            best = (score, shift, beta, residual)
    _, shift, beta, residual = best
    x = columns[:len(y) - shift]
    unscaled = np.linalg.pinv(x.T @ x)
    out = []
    for axis in range(3):
        variance = np.diag(unscaled) * float(residual[:, axis] @ residual[:, axis]) / max(len(x) - 8, 1)
        s, c = beta[:4, axis], beta[4:, axis]
        amplitude = np.hypot(s, c)
        var_amplitude = (s**2 * variance[:4] + c**2 * variance[4:]) / np.maximum(amplitude**2, 1e-300)
        out.append(Estimate.normal(float(amplitude.mean()), float(np.sqrt(var_amplitude.sum()) / 4)))
    fitted = np.zeros_like(y)
    fitted[shift:] = columns[:len(y) - shift] @ beta
    return (out[0], out[1], out[2]), fitted


def noise_level(gyro: np.ndarray, dt: float, top_rotor_hz: float) -> tuple[float, str]:
    """rad/s: the white noise from the spectrum's median level in NOISE_BAND_HZ, or where the rotors
    may reach it, from the spread above the rates' band."""
    low, high = NOISE_BAND_HZ[0], min(NOISE_BAND_HZ[1], 0.45 / dt)
    if top_rotor_hz < low and high > low:
        freq, psd = welch(gyro, fs=1.0 / dt, nperseg=min(1024, len(gyro)), axis=0)
        band = (freq >= low) & (freq <= high)
        level = np.median(psd[band], axis=0)  # one-sided density of white noise: 2σ²·dt
        how = f"the gyro spectrum's level at {low:.0f}-{high:.0f} Hz"
        return float(np.median(np.sqrt(level / (2 * dt)))), how
    spread = np.median(np.std(_high(gyro, dt), axis=0)) / np.sqrt(1 - 2 * SMOOTH_HZ * dt)
    return float(spread), f"the gyro's spread above {SMOOTH_HZ:.0f} Hz"


def vibration_from_power(log: FlightLog, speed: np.ndarray, noise: float,
                         blocks: int = 20) -> tuple[Estimate, Estimate, Estimate]:
    """Without rpm the rotors' angles are unknown, but not their power: with the rotors out of
    step, the vibration's mean square is a²·Σ_i ω_i⁴/2 (ω the modelled speeds), on top of the
    noise's share above the rates' band. Per axis, its interval from `blocks` stretches."""
    dt = log.dt
    power = _high(log.gyro, dt) ** 2 - noise**2 * (1 - 2 * SMOOTH_HZ * dt)
    drive = (speed**4).sum(axis=1) / 2
    parts = [np.sqrt(np.maximum(p.mean(axis=0), 0.0) / d.mean())
             for p, d in zip(np.array_split(power, blocks), np.array_split(drive, blocks), strict=True)]
    whole = np.sqrt(np.maximum(power.mean(axis=0), 0.0) / drive.mean())
    spread = np.std(parts, axis=0, ddof=1) / np.sqrt(blocks)
    x, y, z = (Estimate.normal(float(whole[axis]), float(spread[axis])) for axis in range(3))
    return x, y, z


def fit_gyro(log: FlightLog, top_rotor_speed: float, speed: np.ndarray) -> GyroFit:
    """`top_rotor_speed` (rad/s): the fastest the rotors may turn, where the log has no rpm;
    `speed` (T, 4): the rotor speeds the rate fit used (modelled ones without rpm)."""
    if log.rotor_speed is None:
        noise, how = noise_level(log.gyro, log.dt, top_rotor_speed / (2 * np.pi))
        return GyroFit(vibration_from_power(log, speed, noise), noise, how, from_angles=False)
    vibration = fit_vibration(log)
    gyro = log.gyro if vibration is None else log.gyro - vibration[1]
    noise, how = noise_level(gyro, log.dt, float(log.rotor_speed.max()) / (2 * np.pi))
    if vibration is not None:
        how += ", the fitted vibration taken out"
    if vibration is None:
        return GyroFit(vibration_from_power(log, log.rotor_speed, noise), noise, how, from_angles=False)
    return GyroFit(vibration[0], noise, how, from_angles=True)
