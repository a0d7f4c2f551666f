"""Randomisation ranges relative to whatever airframe they are applied to.

A relative file (`airframes/relative.randomization.json`, `"relative": true`) gives each
parameter's range as factors of a reference the airframe itself sets: its own mass,
inertia and motor constants ("nominal"), or a physical estimate of an effect on that
airframe (rotor inflow damping by momentum theory, the rotor inertia its motor could
spin up, the battery a hover current implies), or plain values where an effect does not
scale with the airframe (latencies, gyro noise: "absolute"). `absolute_ranges` turns it
into the absolute file `sim_bridge.randomization` validates, for one airframe.

Every reference is calibrated on the Iris, whose ranges (iris.randomization.json) are
the estimates these generalise: each constant below says which Iris figure it comes from.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.airframe_file import GRAVITY
from fcemu.sim_bridge.randomization_parameters import PARAMETERS, RandomizationError, known_parameters

AIR_DENSITY = 1.225  # kg/m³, ISA sea level
# PX4 SITL's Iris rotor drag (gazebo_motor_model rotorDragCoefficient) for its 10-inch props; the
# in-plane drag of a rotor grows with disc area × tip speed, so about with R³ at a given rotor speed.
IRIS_ROTOR_DRAG = 8.06428e-5  # N per (rad/s · m/s)
IRIS_ROTOR_RADIUS = 0.127  # m
# Figure of merit × motor and ESC efficiency: the Iris+'s ~15.5 A hover (5.1 Ah, ~20 min) over the
# ideal induced power of its rotors at 12.6 V.
POWER_EFFICIENCY = 0.45
# The Iris pack's 0.03 Ω drops 3.7 % of its 12.6 V at its 15.5 A hover current.
RESISTANCE_DROP = 0.037
# The Iris+ hovers ~20 min on its 5.1 Ah pack (18360 A·s at 15.5 A): the pack's charge in hover time.
HOVER_ENDURANCE_S = 1184.0
EMPTY_DROP = 1.0 - 3.5 / 4.2  # a LiPo cell from full (4.2 V) to empty (3.5 V), as a share of full


def hover_thrust(af: Airframe) -> float:
    return af.mass * GRAVITY / 4


def induced_velocity(af: Airframe) -> float:
    """Momentum theory's hover inflow through one rotor disc, m/s."""
    return math.sqrt(hover_thrust(af) / (2 * AIR_DENSITY * math.pi * af.rotor_radius**2))


def inflow_damping(af: Airframe, axis: int) -> float:
    """Roll (axis 0) or pitch (1) rate damping, N·m·s/rad: a rotor rising at v loses T/(2 v_h)·v of thrust."""
    arms = af.rotor_positions[:, 1 - axis]  # roll: the rotors' y; pitch: their x
    return float(hover_thrust(af) / (2 * induced_velocity(af)) * (arms**2).sum())


def rotor_drag_damping_yaw(af: Airframe) -> float:
    """Yaw rate damping, N·m·s/rad: each rotor's in-plane drag k_d·ω·v at its arm, v = r·Ω."""
    drag = IRIS_ROTOR_DRAG * (af.rotor_radius / IRIS_ROTOR_RADIUS) ** 3
    return float(drag * af.hover_rotor_speed() * (af.rotor_positions[:, :2] ** 2).sum())


def motor_torque_bound(af: Airframe) -> float:
    """Effective rotor inertia, kg·m², the motor's lag allows: drag torque at top speed over the
    spin-up rate ω_max/τ_up (the iris_realistic.json estimate)."""
    m = af.motor
    return m.km * m.kf * m.max_rotor_speed * m.tau_up


def current_per_thrust(af: Airframe) -> float:
    """A per N^1.5 of each rotor: ideal induced power T^1.5/sqrt(2ρA) over the efficiency and voltage."""
    disc = math.pi * af.rotor_radius**2
    return 1.0 / (math.sqrt(2 * AIR_DENSITY * disc) * POWER_EFFICIENCY * af.battery_voltage_full)


def hover_current(af: Airframe) -> float:
    return 4 * current_per_thrust(af) * hover_thrust(af) ** 1.5


def pack_charge(af: Airframe) -> float:
    return hover_current(af) * HOVER_ENDURANCE_S


REFERENCES: dict[str, Callable[[Airframe], float]] = {
    "absolute": lambda af: 1.0,
    "inflow_damping_roll": lambda af: inflow_damping(af, 0),
    "inflow_damping_pitch": lambda af: inflow_damping(af, 1),
    "rotor_drag_damping_yaw": rotor_drag_damping_yaw,
    "motor_torque_bound": motor_torque_bound,
    "per_hover_speed_squared": lambda af: 1.0 / af.hover_rotor_speed() ** 2,
    "current_per_thrust": current_per_thrust,
    "pack_resistance": lambda af: RESISTANCE_DROP * af.battery_voltage_full / hover_current(af),
    "sag_per_charge": lambda af: EMPTY_DROP * af.battery_voltage_full / pack_charge(af),
    "pack_charge": pack_charge,
}
NOMINAL = "nominal"  # the airframe's own value: mass, inertia, motor constants
INERTIA_AXES = ("inertia_xx", "inertia_yy", "inertia_zz")


def is_relative(raw: Any) -> bool:
    return isinstance(raw, dict) and raw.get("relative") is True


def absolute_ranges(raw: dict, airframe: Airframe, where: str) -> dict:
    """The relative file `raw` on `airframe`, as an absolute randomisation file's JSON object."""
    params = known_parameters(raw, where)
    out = {key: _absolute(key, entry, airframe, f"{where}: {key}") for key, entry in params.items()}
    if all(key in out for key in INERTIA_AXES):
        _rigid(out)
    return {"airframe": airframe.name, "about": f"{where} on {airframe.name}", "parameters": out}


def _absolute(key: str, entry: Any, airframe: Airframe, at: str) -> dict:
    if not isinstance(entry, dict):
        raise RandomizationError(f"{at}: expected an object with of, range, unit and source")
    missing = sorted({"of", "range", "unit", "source"} - set(entry))
    if missing:
        raise RandomizationError(f"{at}: missing {missing}")
    kind = PARAMETERS[key].kind
    of, factors = entry["of"], entry["range"]
    allowed = [NOMINAL] if kind == "scale" else ["absolute"] if kind == "ticks" else list(REFERENCES)
    if of not in allowed:
        raise RandomizationError(f"{at}: \"of\" must be one of {allowed} for a {kind} parameter, got {of!r}")
    numbers = isinstance(factors, list) and len(factors) == 2 and all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
        for v in factors)
    if not numbers or factors[0] > factors[1]:
        raise RandomizationError(f"{at}: range must be [lo, hi] with 0 <= lo <= hi, got {factors!r}")
    nominal = PARAMETERS[key].nominal(airframe)
    if kind == "scale" and not factors[0] <= 1.0 <= factors[1]:
        raise RandomizationError(f"{at}: factors of the nominal must hold 1, got {factors!r}")
    reference = nominal if of == NOMINAL else REFERENCES[of](airframe)
    if of == "absolute":
        return {"unit": entry["unit"], "nominal": nominal, "range": list(factors), "source": entry["source"]}
    return {"unit": entry["unit"], "nominal": nominal, "range": [f * reference for f in factors],
            "source": f"{entry['source']} ({factors[0]:g} to {factors[1]:g} x {of} {reference:.4g})"}


def _rigid(out: dict) -> None:
    """Keep every draw a rigid body (I_i <= I_j + I_k at the others' lowest draws): an axis's top is
    capped, and where even its nominal would break that, the other two axes' lows are raised."""
    for _ in range(2):  # raising one axis's low can only loosen the others' caps
        for key in INERTIA_AXES:
            others = [out[k] for k in INERTIA_AXES if k != key]
            entry = out[key]
            cap = sum(o["range"][0] for o in others)
            if entry["range"][1] <= cap:
                continue
            if cap < entry["nominal"]:
                share = min(entry["nominal"] / sum(o["nominal"] for o in others) * (1 + 1e-12), 1.0)
                for o in others:
                    o["range"][0] = max(o["range"][0], share * o["nominal"])
                    o["source"] += f"; low raised to {o['range'][0]:.4g} so that {key} stays a rigid body"
                cap = sum(o["range"][0] for o in others)
            entry["range"][1] = max(min(entry["range"][1], cap), entry["nominal"])
            entry["source"] += f"; capped at {entry['range'][1]:.4g}, the other axes' lowest sum (rigid body)"
