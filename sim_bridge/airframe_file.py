"""Reading and checking an airframe file before the twin is built from it.

Every problem with a file (not JSON, a missing or misspelt field, a wrong type, a number
no quadrotor could have) is one `AirframeError` naming the file and the field, which
`fcemu` prints as one line. The checks are on the file's own numbers, so a twin is never
built from an airframe MuJoCo would refuse or that could not lift itself.
"""

from __future__ import annotations

import difflib
import json
import math
from pathlib import Path
from typing import Any

from fcemu.firmware.errors import UserError

GRAVITY = 9.81
CENTRE_CLEARANCE_M = 0.005  # a rotor closer than this to the centre has no lever arm
CENTRE_TOLERANCE = 0.1  # the rotors' centroid may be off the centre of mass by this share of the arm
# Betaflight's Quad X order in FRD axes: 1 rear right, 2 front right, 3 rear left, 4 front left.
QUAD_X_SIGNS = ((-1, 1, "rear right"), (1, 1, "front right"), (-1, -1, "rear left"), (1, -1, "front left"))

REQUIRED = ("name", "base_mass_kg", "base_inertia_kg_m2", "base_box_m", "rotor_mass_kg", "rotor_radius_m",
            "motors", "motor", "landing_gear_half_height_m")
OPTIONAL = ("source", "sources", "frame", "base", "rotor_body_inertia_kg_m2", "effects")
MOTOR_REQUIRED = ("max_rotor_speed_rad_s", "thrust_coefficient_N_per_rad_s2", "moment_constant_m",
                  "time_constant_up_s", "time_constant_down_s")
MOTOR_OPTIONAL = ("pwm_min_us", "pwm_max_us", "poles")
ROTOR_FIELDS = ("name", "position_m", "spin")
# What "sources" may cite: each number of the file (the motors' positions and spins together).
SOURCED = ("base_mass_kg", "base_inertia_kg_m2", "base_box_m", "rotor_mass_kg", "rotor_body_inertia_kg_m2",
           "rotor_radius_m", "motors", "landing_gear_half_height_m",
           *(f"motor.{key}" for key in MOTOR_REQUIRED + MOTOR_OPTIONAL))


class AirframeError(UserError, ValueError):
    """An airframe file that cannot be read or describes no flyable Quad X."""

    def __init__(self, path: Path | str, field: str, problem: str) -> None:
        super().__init__(f"{path}: {field}: {problem}" if field else f"{path}: {problem}")


def read_json(path: Path) -> dict:
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise AirframeError(path, "", f"cannot read as JSON: {exc}") from None
    if not isinstance(raw, dict):
        raise AirframeError(path, "", f"expected a JSON object, got {type(raw).__name__}")
    return raw


def check_keys(path: Path, where: str, raw: dict, required: tuple[str, ...],
               optional: tuple[str, ...]) -> None:
    """Unknown keys (with the closest known name) first, then missing ones."""
    known = required + optional
    for key in raw:
        if key not in known:
            raise AirframeError(path, f"{where}{key}", f"unknown field{suggestion(key, known)}")
    for key in required:
        if key not in raw:
            raise AirframeError(path, f"{where}{key}", "missing")


def suggestion(key: str, known: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(key, known, n=1)
    return f"; did you mean {close[0]!r}?" if close else f"; known: {', '.join(known)}"


def number(path: Path, field: str, value: Any, low: float | None = 0.0, strict: bool = True) -> float:
    """A finite number; above `low` (strictly unless `strict` is False) when `low` is given."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise AirframeError(path, field, f"expected a number, got {json.dumps(value)}")
    if not math.isfinite(value):
        raise AirframeError(path, field, f"must be finite, got {value}")
    if low is not None and (value <= low if strict else value < low):
        raise AirframeError(path, field, f"must be {'>' if strict else '>='} {low:g}, got {value:g}")
    return float(value)


def vector(path: Path, field: str, value: Any, low: float | None = 0.0,
           strict: bool = True) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != 3:
        raise AirframeError(path, field, f"expected 3 numbers, got {json.dumps(value)}")
    return tuple(number(path, f"{field}[{i}]", v, low, strict) for i, v in enumerate(value))


def rigid_body(path: Path, field: str, inertia: tuple[float, ...]) -> None:
    """Each principal moment at most the sum of the other two (MuJoCo refuses any other body)."""
    for i, axis in enumerate("xyz"):
        others = sum(inertia) - inertia[i]
        if inertia[i] > others * (1 + 1e-9):
            raise AirframeError(path, field, f"I_{axis}{axis} {inertia[i]:g} exceeds the other two axes' sum "
                                             f"{others:g}: no rigid body has such an inertia")


def check_airframe_file(path: Path, raw: dict) -> None:
    """Every field of a whole (variant-merged) airframe file: names, types and physical values."""
    check_keys(path, "", raw, REQUIRED, OPTIONAL)
    if not isinstance(raw["name"], str) or not raw["name"]:
        raise AirframeError(path, "name", "must be a non-empty string")
    mass = number(path, "base_mass_kg", raw["base_mass_kg"])
    rotor_mass = number(path, "rotor_mass_kg", raw["rotor_mass_kg"], strict=False)
    rigid_body(path, "base_inertia_kg_m2", vector(path, "base_inertia_kg_m2", raw["base_inertia_kg_m2"]))
    vector(path, "base_box_m", raw["base_box_m"])
    number(path, "rotor_radius_m", raw["rotor_radius_m"])
    number(path, "landing_gear_half_height_m", raw["landing_gear_half_height_m"], strict=False)
    if "rotor_body_inertia_kg_m2" in raw:
        field = "rotor_body_inertia_kg_m2"
        rigid_body(path, field, vector(path, field, raw[field], strict=False))
    motor = raw["motor"]
    if not isinstance(motor, dict):
        raise AirframeError(path, "motor", "expected an object of the motor constants")
    check_keys(path, "motor.", motor, MOTOR_REQUIRED, MOTOR_OPTIONAL)
    for key in MOTOR_REQUIRED:
        number(path, f"motor.{key}", motor[key])
    pwm_min = number(path, "motor.pwm_min_us", motor.get("pwm_min_us", 1000))
    pwm_max = number(path, "motor.pwm_max_us", motor.get("pwm_max_us", 2000))
    if pwm_min >= pwm_max:
        raise AirframeError(path, "motor.pwm_min_us",
                            f"must be below pwm_max_us, got {pwm_min:g} >= {pwm_max:g}")
    poles = motor.get("poles")
    whole = isinstance(poles, int) and not isinstance(poles, bool)
    if poles is not None and not (whole and poles >= 2 and poles % 2 == 0):
        raise AirframeError(path, "motor.poles", f"must be an even whole number >= 2 (magnet poles of a "
                                                 f"brushless motor) or null (brushed), "
                                                 f"got {json.dumps(poles)}")
    positions = _rotors(path, raw["motors"])
    kf, omega = motor["thrust_coefficient_N_per_rad_s2"], motor["max_rotor_speed_rad_s"]
    weight = (mass + len(positions) * rotor_mass) * GRAVITY
    if 4 * kf * omega**2 <= weight:
        raise AirframeError(path, "motor.max_rotor_speed_rad_s",
                            f"four rotors at {omega:g} rad/s lift {4 * kf * omega**2:.4g} N, not the weight "
                            f"{weight:.4g} N: the airframe cannot hover")
    sources = raw.get("sources", {})
    if not isinstance(sources, dict) or not all(isinstance(v, str) for v in sources.values()):
        raise AirframeError(path, "sources", "expected an object of field name -> citation text")
    check_keys(path, "sources.", sources, (), SOURCED)
    effects = raw.get("effects", {})
    if not isinstance(effects, dict):
        raise AirframeError(path, "effects", "expected an object of effects, each {value, source}")


def _rotors(path: Path, motors: Any) -> list[tuple[float, ...]]:
    """Four rotors in Betaflight's Quad X order around the centre, spins cancelling in diagonal pairs."""
    if not isinstance(motors, list) or len(motors) != 4:
        count = len(motors) if isinstance(motors, list) else type(motors).__name__
        raise AirframeError(path, "motors", f"a Quad X airframe needs a list of 4 motors, found {count}")
    positions = []
    for i, rotor in enumerate(motors):
        where = f"motors[{i}]"
        if not isinstance(rotor, dict):
            raise AirframeError(path, where, "expected an object with name, position_m and spin")
        check_keys(path, f"{where}.", rotor, ROTOR_FIELDS, ())
        if rotor["spin"] not in ("cw", "ccw"):
            raise AirframeError(path, f"{where}.spin",
                                f"must be \"cw\" or \"ccw\", got {json.dumps(rotor['spin'])}")
        x, y, z = vector(path, f"{where}.position_m", rotor["position_m"], low=None)
        sx, sy, place = QUAD_X_SIGNS[i]
        if math.hypot(x, y) < CENTRE_CLEARANCE_M:
            raise AirframeError(path, f"{where}.position_m", f"a rotor {math.hypot(x, y) * 1000:.1f} mm from "
                                                             f"the centre has no lever arm")
        if x * sx <= 0 or y * sy <= 0:
            raise AirframeError(path, f"{where}.position_m",
                                f"motor {i + 1} is the {place} one in Betaflight's Quad X order (FRD: "
                                f"x {'>' if sx > 0 else '<'} 0, y {'>' if sy > 0 else '<'} 0), "
                                f"got ({x:g}, {y:g})")
        positions.append((x, y, z))
    arm = sum(math.hypot(x, y) for x, y, _ in positions) / 4
    cx, cy = (sum(p[k] for p in positions) / 4 for k in (0, 1))
    if math.hypot(cx, cy) > CENTRE_TOLERANCE * arm:
        raise AirframeError(path, "motors", f"the rotors' centre ({cx:.4g}, {cy:.4g}) m is off the centre "
                                            f"of mass by more than {CENTRE_TOLERANCE:.0%} of the arm "
                                            f"({arm:.4g} m)")
    spins = [rotor["spin"] for rotor in motors]
    if spins[0] != spins[3] or spins[1] != spins[2] or spins[0] == spins[1]:
        raise AirframeError(path, "motors", f"spins {spins} do not cancel: a Quad X needs the diagonal "
                                            f"pairs (motors 1 and 4, 2 and 3) to spin the same way, each "
                                            f"pair opposite the other")
    return positions
