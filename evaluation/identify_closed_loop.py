"""The twin refined in closed loop: the log's own tune flies it on the log's setpoints, and the
few numbers a closed-loop log tells worst are moved until the twin's rates follow the quad's.

A log flown by a pilot through a PID is a closed loop: the motor commands answer the gyro, so a
least-squares fit of the rates' acceleration to the commands (`identify.fit_rates`) is biased
where the gyro's noise and the vibration drive the commands, and a real quad's motors, props and
filters are not quite the twin's first-order lag. The controller that flew the log is known (its
header's tune, `blackbox_tune.log_tune`), so the twin is flown as the quad was, on a stretch of
the log, and the mismatch of its rates against the log's, each axis's squared error over the
log's variance, is minimised over each axis's control effectiveness, the motors' time constant
and the rotors' spin-up reaction, from the least-squares twin, at each gyro delay near its fit.
This is the output-error method of system identification; its price is a few dozen flights.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

from fcemu.evaluation.identify_log import FlightLog
from fcemu.evaluation.replay import fly_log, span_of
from fcemu.sim_bridge.airframe import Airframe

STRETCH_S = 8.0  # of the log flown per evaluation: its busiest stretch
FACTOR_BOUND = 8.0  # each scale stays within 1/8 … 8 of the least-squares value
MAX_EVALUATIONS = 60  # per gyro delay tried


@dataclass(frozen=True)
class Refinement:
    airframe: Airframe
    factors: dict[str, float]  # each parameter over its least-squares value
    gyro_delay_ticks: int
    mismatch_before: tuple[float, float, float]  # per axis, squared error over the log's variance
    mismatch_after: tuple[float, float, float]
    flights: int
    stretch_s: tuple[float, float]


def busiest_stretch(log: FlightLog, seconds: float = STRETCH_S) -> tuple[float, float]:
    """The `seconds` of the log whose setpoint moves most, all three axes weighed alike."""
    if log.t[-1] <= seconds:
        return (0.0, float(log.t[-1]))
    n = round(seconds / log.dt)
    moving = np.abs(np.diff(log.setpoint, axis=0))
    moving /= np.maximum(moving.sum(axis=0), 1e-9)
    activity = np.convolve(moving.sum(axis=1), np.ones(n), mode="valid")
    start = float(log.t[int(np.argmax(activity))])
    return (start, start + seconds)


def with_factors(airframe: Airframe, roll: float, pitch: float, yaw: float, tau: float,
                 spin_up: float) -> Airframe:
    """`airframe` with each axis's effectiveness, the motors' time constants and the spin-up
    reaction multiplied; I_zz kept inside what a rigid body allows as roll's and pitch's move."""
    ixx, iyy, izz = airframe.inertia()
    rotors = airframe.inertia() - np.array(airframe.base_inertia)
    new_x, new_y = ixx / roll, iyy / pitch
    body_x, body_y = new_x - rotors[0], new_y - rotors[1]
    if min(body_x, body_y) <= 0:
        raise ValueError("the effectiveness leaves the body no inertia of its own")
    low, high = abs(body_x - body_y), body_x + body_y  # MuJoCo's body, without the rotors, must be rigid
    new_z = float(np.clip(izz - rotors[2], low * 1.02 + 1e-12, high * 0.98)) + rotors[2]
    km = airframe.motor.km * yaw * new_z / izz  # the yaw effectiveness k_F·k_M / I_zz times `yaw`
    m = airframe.motor
    motor = replace(m, km=km, tau_up=m.tau_up * tau, tau_down=m.tau_down * tau)
    inertia = (new_x - rotors[0], new_y - rotors[1], new_z - rotors[2])
    return replace(airframe, base_inertia=tuple(float(v) for v in inertia), motor=motor,
                   rotor_inertia=airframe.rotor_inertia * spin_up * new_z / izz)


def mismatch(log: FlightLog, airframe: Airframe, controller: str) -> np.ndarray:
    """(3,) per axis: the twin's rates flown in closed loop against the log's, squared error over
    the log's variance."""
    flown = fly_log(log, airframe, controller)
    error = np.mean((flown.twin_gyro - flown.log_gyro) ** 2, axis=0)
    scale = np.var(flown.log_gyro, axis=0) + 1e-6
    out = error / scale
    return np.where(np.isfinite(out), np.minimum(out, 100.0), 100.0)


def delays_tried(airframe: Airframe) -> list[int]:
    """The gyro delays the refinement tries, ticks: the least-squares one and up to three shorter."""
    return sorted({max(0, airframe.gyro_delay_ticks - k) for k in range(4)})


def planned_flights(airframe: Airframe) -> int:
    """The most flights `refine` flies: each delay's optimiser's, the twin before and after."""
    return len(delays_tried(airframe)) * MAX_EVALUATIONS + 2


def refine(log: FlightLog, airframe: Airframe, controller: str,
           progress: Callable[[int, int, float], None] | None = None) -> Refinement:
    """The least-squares `airframe` refined by flying it with `controller` on the log's busiest stretch.
    `progress(flights, planned, mismatch)` after each flight: the flights flown, the most there will be
    (fewer once an optimiser stops early), the flight's summed mismatch."""
    stretch = busiest_stretch(log)
    part = span_of(log, stretch)
    delays = delays_tried(airframe)
    flights = 0
    planned = planned_flights(airframe)

    def cost(theta: np.ndarray, delay: int) -> float:
        nonlocal flights
        flights += 1
        factors = np.exp(np.clip(theta, -np.log(FACTOR_BOUND), np.log(FACTOR_BOUND)))
        try:
            candidate = replace(with_factors(airframe, *factors), gyro_delay_ticks=delay)
            value = float(mismatch(part, candidate, controller).sum())
        except ValueError:  # no rigid body: MuJoCo refuses it
            value = 300.0
        if progress is not None:
            progress(flights + 1, planned, value)
        return value

    before = mismatch(part, airframe, controller)
    best = None
    for i, delay in enumerate(delays):
        result = minimize(cost, np.zeros(5), args=(delay,), method="Nelder-Mead",
                          options={"maxfev": MAX_EVALUATIONS, "xatol": 0.02, "fatol": 1e-3,
                                   "initial_simplex": np.vstack([np.zeros(5), 0.5 * np.eye(5)])})
        if best is None or result.fun < best[0]:
            best = (float(result.fun), delay, result.x)
        planned = flights + (len(delays) - i - 1) * MAX_EVALUATIONS + 2
    _, delay, theta = best
    factors = np.exp(np.clip(theta, -np.log(FACTOR_BOUND), np.log(FACTOR_BOUND)))
    refined = replace(with_factors(airframe, *factors), gyro_delay_ticks=delay)
    after = mismatch(part, refined, controller)
    if progress is not None:
        progress(flights + 2, flights + 2, float(after.sum()))
    if after.sum() >= before.sum():
        refined, factors, delay, after = airframe, np.ones(5), airframe.gyro_delay_ticks, before
    names = ("roll_effectiveness", "pitch_effectiveness", "yaw_effectiveness", "motor_time_constant",
             "spin_up_reaction")
    return Refinement(refined, {k: float(v) for k, v in zip(names, factors, strict=True)}, delay,
                      tuple(map(float, before)), tuple(map(float, after)), flights + 2, stretch)


def refined_document(document: dict, refinement: Refinement, log_name: str) -> dict:
    """The airframe file with the refined numbers, each source saying by how much and why."""
    doc = json.loads(json.dumps(document))
    af, f = refinement.airframe, refinement.factors
    how = (f"refined in closed loop: the log's own tune flying the twin on {log_name}'s setpoints "
           f"{refinement.stretch_s[0]:.1f}-{refinement.stretch_s[1]:.1f} s, the rates' mismatch "
           f"{sum(refinement.mismatch_before):.3f} → {sum(refinement.mismatch_after):.3f}")
    doc["base_inertia_kg_m2"] = list(af.base_inertia)
    doc["sources"]["base_inertia_kg_m2"] += (f"; {how}: roll's effectiveness ×{f['roll_effectiveness']:.3g}, "
                                             f"pitch's ×{f['pitch_effectiveness']:.3g}")
    motor = doc["motor"]
    motor.update(moment_constant_m=af.motor.km, time_constant_up_s=af.motor.tau_up,
                 time_constant_down_s=af.motor.tau_down)
    doc["sources"]["motor.moment_constant_m"] = (
        doc["sources"].get("motor.moment_constant_m", "")
        + f"; {how}: yaw's effectiveness ×{f['yaw_effectiveness']:.3g}")
    for key in ("up", "down"):
        doc["sources"][f"motor.time_constant_{key}_s"] += f"; {how}: ×{f['motor_time_constant']:.3g}"
    effects = doc["effects"]
    effects["rotor_inertia_kg_m2"]["value"] = af.rotor_inertia
    effects["rotor_inertia_kg_m2"]["source"] += f"; {how}: ×{f['spin_up_reaction']:.3g}"
    effects["gyro_delay_ticks"]["value"] = refinement.gyro_delay_ticks
    effects["gyro_delay_ticks"]["source"] += f"; {how}: {refinement.gyro_delay_ticks} ticks flew it best"
    return doc
