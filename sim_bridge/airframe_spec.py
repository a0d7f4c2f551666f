"""The firmware's view of an airframe file (`firmware.airframe_spec`), and the envelope a policy
trained on it, or across its randomisation, was made for."""

from __future__ import annotations

from itertools import product

import numpy as np

from fcemu.firmware.airframe_spec import AirframeSpec, Envelope
from fcemu.sim_bridge.airframe import Airframe, load_airframe
from fcemu.sim_bridge.randomization import PARAMETERS, Randomization, load_randomization

GRAVITY = 9.81
# Where a policy's randomisation is not known, the envelope is its airframe's scales ± this.
UNKNOWN_RANGE_MARGIN = 0.25


def inertia(airframe: Airframe) -> np.ndarray:
    """Roll, pitch, yaw inertia (kg·m²): the base's plus the rotors as point masses at their positions."""
    x, y, z = airframe.rotor_positions.T
    arms = np.array([y**2 + z**2, x**2 + z**2, x**2 + y**2]).sum(axis=1)
    return np.asarray(airframe.base_inertia) + airframe.rotor_mass * arms


def max_angular_acceleration(airframe: Airframe) -> tuple[float, float, float]:
    """Per axis (rad/s²), what full differential thrust gives in the weaker direction: the rotors
    on one side (of one spin, for yaw) at top speed, the others stopped."""
    m = airframe.motor
    thrust = m.kf * m.max_rotor_speed**2
    x, y, _ = airframe.rotor_positions.T
    roll = min(np.abs(y[y < 0]).sum(), y[y > 0].sum())
    pitch = min(np.abs(x[x < 0]).sum(), x[x > 0].sum())
    yaw = min((airframe.spin > 0).sum(), (airframe.spin < 0).sum()) * m.km
    torque = thrust * np.array([roll, pitch, yaw])
    return tuple(float(v) for v in torque / inertia(airframe))  # type: ignore[return-value]


def thrust_to_weight(airframe: Airframe) -> float:
    m = airframe.motor
    return float(4 * m.kf * m.max_rotor_speed**2 / (airframe.mass * GRAVITY))


def airframe_spec(airframe: Airframe | str) -> AirframeSpec:
    """What the firmware is configured with for `airframe` (an Airframe, a shipped name or a file)."""
    af = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)
    m = af.motor
    return AirframeSpec(name=af.name, max_rotor_speed=m.max_rotor_speed, pwm_min=m.pwm_min, pwm_max=m.pwm_max,
                        motor_poles=getattr(m, "poles", None), hover_throttle=af.hover_throttle(GRAVITY),
                        thrust_to_weight=thrust_to_weight(af),
                        max_angular_acceleration=max_angular_acceleration(af),
                        motor_tau_up=m.tau_up, motor_tau_down=m.tau_down)


def randomization_corners(ranges: Randomization, base: Airframe) -> list[Airframe]:
    """`base` at every corner of the ranges of mass, inertia and motor constants: each scale of
    `AirframeSpec` is monotonic in each of them, so the corners bound every draw's."""
    scaled = [p for p in ranges.parameters if PARAMETERS[p.key].kind == "scale"]
    corners = []
    for ends in product(*[(p.lo / p.nominal, p.hi / p.nominal) for p in scaled]):
        keywords: dict = {}
        for p, factor in zip(scaled, ends, strict=True):
            _, keyword, axis, _ = PARAMETERS[p.key]
            if axis is None:
                keywords[keyword] = factor
            else:
                axes = list(keywords.get(keyword, (1.0, 1.0, 1.0)))
                axes[axis] = factor
                keywords[keyword] = tuple(axes)
        corners.append(base.scaled(**keywords))
    return corners


def envelope(airframe: Airframe | str, randomization: str | Randomization | None = None) -> Envelope:
    """The scales of every airframe a policy trained on `airframe` across `randomization` met (its
    corners); without one, the airframe's own scales ± UNKNOWN_RANGE_MARGIN."""
    af = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)
    if randomization is None:
        return Envelope.around([airframe_spec(af)]).widened(UNKNOWN_RANGE_MARGIN)
    ranges = randomization if isinstance(randomization, Randomization) else load_randomization(randomization)
    ranges.check_airframe(af)
    return Envelope.around([airframe_spec(c) for c in randomization_corners(ranges, af)])
