"""The firmware's view of an airframe file (`firmware.airframe_spec`), and the envelope a policy
trained on it, or across its randomisation, was made for."""

from __future__ import annotations

from itertools import product

from fcemu.firmware.airframe_spec import AirframeSpec, Envelope
from fcemu.sim_bridge.airframe import Airframe, load_airframe
from fcemu.sim_bridge.airframe_file import GRAVITY
from fcemu.sim_bridge.randomization import PARAMETERS, Randomization, ranges_for

# Where a policy's randomisation is not known, the envelope is its airframe's scales ± this.
UNKNOWN_RANGE_MARGIN = 0.25


def airframe_spec(airframe: Airframe | str) -> AirframeSpec:
    """What the firmware is configured with for `airframe` (an Airframe, a shipped name or a file)."""
    af = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)
    m = af.motor
    return AirframeSpec(name=af.name, max_rotor_speed=m.max_rotor_speed, pwm_min=m.pwm_min, pwm_max=m.pwm_max,
                        motor_poles=m.poles, hover_throttle=af.hover_throttle(GRAVITY),
                        thrust_to_weight=af.thrust_to_weight(GRAVITY),
                        max_angular_acceleration=tuple(map(float, af.max_angular_acceleration(GRAVITY))),
                        motor_tau_up=m.tau_up, motor_tau_down=m.tau_down, tune_of=af.tune_of or af.name,
                        props_out=bool(af.spin[0] > 0), loop_delay_ticks=af.loop_delay_ticks)


def randomization_corners(ranges: Randomization, base: Airframe) -> list[Airframe]:
    """`base` at every corner of the ranges of mass, inertia and motor constants, and where the
    ranges cross thrust-to-weight 2, at the ends of that line: every scale of `AirframeSpec` is
    monotonic in each of them but the top angular acceleration, whose thrust margin
    min(T_max − T_hover, T_hover) peaks there; so these bound every draw's scales."""
    scaled = [p for p in ranges.parameters if PARAMETERS[p.key].kind == "scale"]
    ends = [(p.lo / p.nominal, p.hi / p.nominal) for p in scaled]
    keys = [p.key for p in scaled]
    points = [list(c) for c in product(*ends)]
    if "mass" in keys and "kf" in keys:
        m, k = keys.index("mass"), keys.index("kf")
        ratio = base.thrust_to_weight(GRAVITY) / 2.0  # T/W = 2 where f_kf = f_mass / ratio
        others = list(product(*[e for i, e in enumerate(ends) if i not in (m, k)]))
        line = [(f, f / ratio) for f in ends[m]] + [(f * ratio, f) for f in ends[k]]
        for f_mass, f_kf in line:
            if ends[m][0] <= f_mass <= ends[m][1] and ends[k][0] <= f_kf <= ends[k][1]:
                for rest in others:
                    point = list(rest)
                    for i, f in sorted(((m, f_mass), (k, f_kf))):
                        point.insert(i, f)
                    points.append(point)
    return [base.scaled(**_keywords(scaled, point)) for point in points]


def _keywords(scaled: list, factors: list[float]) -> dict:
    keywords: dict = {}
    for p, factor in zip(scaled, factors, strict=True):
        _, keyword, axis, _ = PARAMETERS[p.key]
        if axis is None:
            keywords[keyword] = factor
        else:
            axes = list(keywords.get(keyword, (1.0, 1.0, 1.0)))
            axes[axis] = factor
            keywords[keyword] = tuple(axes)
    return keywords


def envelope(airframe: Airframe | str, randomization: str | Randomization | None = None) -> Envelope:
    """The scales of every airframe a policy trained on `airframe` across `randomization` met (its
    corners); without one, the airframe's own scales ± UNKNOWN_RANGE_MARGIN."""
    af = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)
    if randomization is None:
        return Envelope.around([airframe_spec(af)]).widened(UNKNOWN_RANGE_MARGIN)
    ranges = randomization if isinstance(randomization, Randomization) else ranges_for(af, randomization)
    ranges.check_airframe(af)
    return Envelope.around([airframe_spec(c) for c in randomization_corners(ranges, af)])
