"""A log's own flight flown again on a twin, and the twin judged against the log.

The firmware loop flies the twin (on the ball-joint rig, so only the rates and rotors move) on
the log's rate setpoint and collective, at fcemu's 1 kHz, with the controller given (the log's
own tune by default: `blackbox_tune.log_tune`). The twin then answers for what the quad did:
per axis the tracking error's RMS, the step response by PID-Analyzer's method
(`step_response`), and the 50 ms-ahead prediction of the log's rates by the airframe's own
model against the base airframe's. A stretch the twin was not identified from is the check.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fcemu.evaluation.identify import AXES, airframe_accel, levers, predict_ahead, prediction_fit
from fcemu.evaluation.identify_flight import _Excitation
from fcemu.evaluation.identify_log import FlightLog, LogError
from fcemu.evaluation.step_response import StepResponse, step_response
from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.loop import FlightLoop
from fcemu.firmware.timing import LockstepClock
from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sim_bridge.link import InProcessLink
from fcemu.sim_bridge.twin import Twin, hover_state

RATE_HZ = 1000.0
AHEAD_S = 0.05


@dataclass(frozen=True)
class Flown:
    """The log and the twin on one 1 kHz grid over the replayed stretch."""

    t: np.ndarray  # (T,) s into the log's flight
    setpoint: np.ndarray  # (T, 3) rad/s FRD
    throttle: np.ndarray  # (T,) 0..1
    log_gyro: np.ndarray  # (T, 3) rad/s
    twin_gyro: np.ndarray  # (T, 3) rad/s, what the twin's controller read
    log_command: np.ndarray  # (T, 4) 0..1
    twin_command: np.ndarray  # (T, 4) 0..1


@dataclass(frozen=True)
class AxisComparison:
    log_rms: float
    twin_rms: float
    log_step: StepResponse | None
    twin_step: StepResponse | None
    prediction_fit_pct: float
    base_prediction_fit_pct: float


def span_of(log: FlightLog, span: tuple[float, float] | None) -> FlightLog:
    """The stretch `span` (s into the flight, either end None for the log's own) of the log."""
    if span is None:
        return log
    start, end = span
    inside = (log.t >= (start or 0.0)) & (log.t <= (log.t[-1] if end is None else end))
    if inside.sum() * log.dt < 2.0:
        raise LogError(f"{log.path}: --span {start}:{end} holds {inside.sum() * log.dt:.2f} s of the "
                       f"{log.t[-1]:.1f} s flight; at least 2 s needed")
    cut = {name: getattr(log, name)[inside] for name in ("t", "gyro", "command", "rotor_speed", "throttle",
                                                           "setpoint", "battery_v")
           if getattr(log, name) is not None}
    cut["t"] = cut["t"] - cut["t"][0]
    return replace(log, **cut)


def _on_grid(log: FlightLog, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    columns = values.reshape(len(log.t), -1)
    out = np.stack([np.interp(t, log.t, columns[:, i]) for i in range(columns.shape[1])], axis=1)
    return out.reshape((len(t), *values.shape[1:]))


def fly_log(log: FlightLog, airframe: Airframe, controller: str) -> Flown:
    """Fly `airframe`'s twin with `controller` on the log's setpoint and collective."""
    if log.setpoint is None:
        raise LogError(f"{log.path}: no rate setpoint (setpoint[0..2] or rcCommand[0..2]) to fly again")
    t = np.arange(0.0, log.t[-1], 1.0 / RATE_HZ)
    setpoint = _on_grid(log, log.setpoint, t)
    collective = log.throttle if log.throttle is not None else log.command.mean(axis=1)
    throttle = np.clip(_on_grid(log, collective, t), 0.0, 1.0)
    spec = airframe_spec(airframe)
    twin = Twin(airframe, rig="rig", dt=1.0 / RATE_HZ)
    period_us = round(1e6 / RATE_HZ)
    first = twin.reset(0, hover_state(airframe, float(throttle[0])))
    loop = FlightLoop(InProcessLink(twin), first, {"main": load_controller(controller, RATE_HZ, spec)},
                      _Excitation(setpoint, throttle, period_us), LockstepClock(), RATE_HZ, [])
    gyro = np.empty((len(t), 3))
    pwm = np.empty((len(t), 4))
    for k in range(len(t)):
        sample = loop.tick(k * period_us)
        gyro[k] = sample.frame.gyro
        pwm[k] = sample.pwm
    return Flown(t, setpoint, throttle, _on_grid(log, log.gyro, t), gyro,
                 _on_grid(log, log.command, t), (pwm - PWM_MIN) / PWM_SPAN)


def model_speed(log: FlightLog, airframe: Airframe) -> np.ndarray:
    """(T, 4) rad/s: the log's rotor speeds, or the airframe's motors' answer to its commands."""
    if log.rotor_speed is not None:
        return log.rotor_speed
    m = airframe.motor
    target = (np.clip(PWM_MIN + PWM_SPAN * log.command, m.pwm_min, m.pwm_max) - m.pwm_min)
    target *= m.max_rotor_speed / (m.pwm_max - m.pwm_min)
    shift = round(airframe.esc_delay_ticks * 0.001 / log.dt)
    if shift:
        target = np.vstack([np.repeat(target[:1], shift, axis=0), target[:-shift]])
    up, down = 1 - np.exp(-log.dt / m.tau_up), 1 - np.exp(-log.dt / m.tau_down)
    speed = np.empty_like(target)
    w = target[0].copy()
    for k in range(len(target)):
        speed[k] = w
        gap = target[k] - w
        w += np.where(gap > 0, up, down) * gap
    return speed


def prediction_fits(log: FlightLog, airframe: Airframe) -> np.ndarray:
    """(3,) %: the airframe's 50 ms-ahead prediction of the log's rates (`identify.prediction_fit`)."""
    accel = airframe_accel(log, model_speed(log, airframe), airframe, levers(airframe))
    return prediction_fit(log, predict_ahead(log, accel, max(1, round(AHEAD_S / log.dt))))


def compare(log: FlightLog, flown: Flown, airframe: Airframe, base: Airframe) -> dict[str, AxisComparison]:
    """Per axis the log against the twin; `base` predicts with the airframe's spins (the log's)."""
    dt = 1.0 / RATE_HZ
    fit = prediction_fits(log, airframe)
    base_fit = prediction_fits(log, replace(base, spin=airframe.spin))
    out = {}
    for i, axis in enumerate(AXES):
        sp = flown.setpoint[:, i]
        out[axis] = AxisComparison(
            float(np.sqrt(np.mean((sp - flown.log_gyro[:, i]) ** 2))),
            float(np.sqrt(np.mean((sp - flown.twin_gyro[:, i]) ** 2))),
            step_response(sp, flown.log_gyro[:, i], dt), step_response(sp, flown.twin_gyro[:, i], dt),
            float(fit[i]), float(base_fit[i]))
    return out


def _step_json(step: StepResponse | None) -> dict:
    if step is None:
        return {"step_peak": None, "step_rise_ms": None}
    rise = None if not np.isfinite(step.rise_ms) else round(float(step.rise_ms), 2)
    return {"step_peak": round(float(step.peak), 4), "step_rise_ms": rise}


def comparison_json(axes: dict[str, AxisComparison]) -> dict:
    return {axis: {"log": {"tracking_rms_rad_s": round(c.log_rms, 4), **_step_json(c.log_step)},
                   "twin": {"tracking_rms_rad_s": round(c.twin_rms, 4), **_step_json(c.twin_step)},
                   "prediction_fit_pct": round(c.prediction_fit_pct, 2),
                   "base_prediction_fit_pct": round(c.base_prediction_fit_pct, 2)}
            for axis, c in axes.items()}
