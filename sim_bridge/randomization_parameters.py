"""What a randomisation file may draw: the parameter table, and the error every loader raises.

Shared by the absolute ranges (`sim_bridge.randomization`) and the ranges relative to any
airframe (`sim_bridge.relative_ranges`), so neither imports the other's loader.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from fcemu.sim_bridge.airframe import Airframe


class Parameter(NamedTuple):
    nominal: Callable[[Airframe], float]  # the airframe's value
    keyword: str  # the Airframe.scaled keyword it sets
    axis: int | None = None  # for per-axis keywords
    kind: str = "scale"  # scale: a factor of the nominal; value: the drawn value; ticks: a whole number


def _axis(name: str, axis: int) -> Parameter:
    return Parameter(lambda a: getattr(a, name)[axis], name, axis, "value")


def _effect(name: str, kind: str = "value") -> Parameter:
    return Parameter(lambda a: getattr(a, name), name, None, kind)


PARAMETERS: dict[str, Parameter] = {
    "mass": Parameter(lambda a: a.mass, "mass"),
    "inertia_xx": Parameter(lambda a: a.base_inertia[0], "inertia", 0),
    "inertia_yy": Parameter(lambda a: a.base_inertia[1], "inertia", 1),
    "inertia_zz": Parameter(lambda a: a.base_inertia[2], "inertia", 2),
    "kf": Parameter(lambda a: a.motor.kf, "kf"),
    "km": Parameter(lambda a: a.motor.km, "km"),
    "tau_up": Parameter(lambda a: a.motor.tau_up, "tau_up"),
    "tau_down": Parameter(lambda a: a.motor.tau_down, "tau_down"),
    "rate_damping_roll": _axis("rate_damping", 0),
    "rate_damping_pitch": _axis("rate_damping", 1),
    "rate_damping_yaw": _axis("rate_damping", 2),
    "rotor_inertia": _effect("rotor_inertia"),
    "esc_delay_ticks": _effect("esc_delay_ticks", "ticks"),
    "gyro_delay_ticks": _effect("gyro_delay_ticks", "ticks"),
    "gyro_noise_std": _effect("gyro_noise_std"),
    "gyro_vibration_roll": _axis("gyro_vibration", 0),
    "gyro_vibration_pitch": _axis("gyro_vibration", 1),
    "gyro_vibration_yaw": _axis("gyro_vibration", 2),
    "battery_sag_per_charge": _effect("battery_sag_per_charge"),
    "battery_resistance": _effect("battery_resistance"),
    "battery_current_per_thrust": _effect("battery_current_per_thrust"),
    "battery_drawn_at_start": _effect("battery_drawn_at_start"),
    # last: ranges without them draw every other parameter as before
    "esc_telemetry_delay_ticks": _effect("esc_telemetry_delay_ticks", "ticks"),
    "esc_telemetry_loss": _effect("esc_telemetry_loss"),
}
# The ESC telemetry bus. The bus-aware training ranges draw it (iris_sensors, the default's); the
# perturbation ranges (iris, relative) do not: a late bus is judged by the health rules (read
# ahead) and the faults table, and on a perturbed airframe it would mix them into the bar's lines.
BUS_PARAMETERS = frozenset({"esc_telemetry_delay_ticks", "esc_telemetry_loss"})
GYRO_KEYWORDS = frozenset({"gyro_noise_std", "gyro_vibration", "gyro_delay_ticks"})


class RandomizationError(ValueError):
    """A randomisation file that is missing, malformed or inconsistent with its airframe."""


def known_parameters(raw: dict, where: str) -> dict:
    """The file's "parameters" object, refused unless non-empty and every key is in `PARAMETERS`."""
    params = raw.get("parameters")
    if not isinstance(params, dict) or not params:
        raise RandomizationError(f"{where}: \"parameters\" must be a non-empty object")
    unknown = sorted(set(params) - set(PARAMETERS))
    if unknown:
        raise RandomizationError(f"{where}: unknown parameter(s) {unknown}; known: {list(PARAMETERS)}")
    return params
