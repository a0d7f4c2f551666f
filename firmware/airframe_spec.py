"""What the firmware knows of the airframe it flies, and the envelope of airframes a policy was made for.

`AirframeSpec` is what a real flight controller is configured with (Betaflight's
`motor_poles`, PX4's `MPC_THR_HOVER`, the motor protocol's PWM range) plus the scales a
policy's envelope compares: the simulated world (`sim_bridge.airframe_spec`) builds it from an
airframe file; the firmware never reads one. `Envelope` is the range of each scale a policy was
trained across, carried in its metadata as `fcemu.envelope` (JSON) beside `fcemu.airframe`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass

# A scale on a bound of the envelope, or within this fraction beyond it, is inside: exported
# numbers are rounded, and an airframe whose file rounds its constants differently is the same one.
ENVELOPE_SLACK = 0.01
# Each envelope scale: its words in a message and its unit.
SCALES: dict[str, tuple[str, str]] = {
    "thrust_to_weight": ("thrust-to-weight", ""),
    "max_rotor_speed": ("top rotor speed", " rad/s"),
    "hover_throttle": ("hover throttle", ""),
    "max_angular_acceleration": ("top angular acceleration", " rad/s²"),
    "motor_tau_up": ("motor spin-up time constant", " s"),
    "motor_tau_down": ("motor spin-down time constant", " s"),
}
AXES = ("roll", "pitch", "yaw")


@dataclass(frozen=True)
class AirframeSpec:
    name: str
    max_rotor_speed: float  # rad/s at pwm_max
    pwm_min: float  # µs
    pwm_max: float  # µs
    motor_poles: int | None  # magnets of the motors (Betaflight's motor_poles); None: not known
    hover_throttle: float  # the collective (0..1) that holds the weight (PX4's MPC_THR_HOVER)
    thrust_to_weight: float  # all rotors at max_rotor_speed over the weight
    max_angular_acceleration: tuple[float, float, float]  # rad/s², roll, pitch, yaw
    motor_tau_up: float  # s
    motor_tau_down: float  # s
    tune_of: str | None = None  # whose PID tune it flies (a variant of the same physics: its base's)
    props_out: bool = False  # motor 1 spins counter-clockwise: the mixer's yaw reversed (Betaflight's)
    loop_delay_ticks: int = 0  # ticks of the ESC protocol's and gyro filters' delays (Airframe's)

    def scale(self, key: str) -> float | tuple[float, ...]:
        return getattr(self, key)


Range = tuple[float, float]


@dataclass(frozen=True)
class Envelope:
    """For each scale of `SCALES`, the [lo, hi] a policy was trained across (per axis where it has axes)."""

    ranges: Mapping[str, Range | tuple[Range, ...]]

    @classmethod
    def around(cls, specs: list[AirframeSpec]) -> Envelope:
        """The smallest envelope holding every airframe of `specs` (e.g. the corners of a randomisation)."""
        ranges: dict[str, Range | tuple[Range, ...]] = {}
        for key in SCALES:
            values = [s.scale(key) for s in specs]
            if isinstance(values[0], tuple):
                ranges[key] = tuple((min(v[i] for v in values), max(v[i] for v in values))  # type: ignore[index]
                                    for i in range(len(values[0])))
            else:
                ranges[key] = (min(values), max(values))  # type: ignore[type-var]
        return cls(ranges)

    def widened(self, fraction: float) -> Envelope:
        """Each range stretched by ±`fraction` of its bounds (a margin where no randomisation is known)."""
        def widen(r: Range) -> Range:
            return (r[0] * (1.0 - fraction), r[1] * (1.0 + fraction))

        return Envelope({k: tuple(map(widen, r)) if isinstance(r[0], tuple) else widen(r)  # type: ignore[arg-type]
                         for k, r in self.ranges.items()})

    def to_json(self) -> str:
        return json.dumps({k: [list(x) for x in r] if isinstance(r[0], tuple) else list(r)
                           for k, r in self.ranges.items()}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> Envelope:
        """ValueError, with what is wrong, for anything but a range per scale (finite, 0 <= lo <= hi)."""
        try:
            raw = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise ValueError(f"not JSON ({exc})") from None
        if not isinstance(raw, dict) or set(raw) - set(SCALES) or not raw:
            raise ValueError(f"not an object of ranges of {sorted(SCALES)}")
        ranges: dict[str, Range | tuple[Range, ...]] = {}
        for key, value in raw.items():
            if key == "max_angular_acceleration":
                if not isinstance(value, list) or len(value) != 3:
                    raise ValueError(f"{key} needs one range per axis")
                ranges[key] = tuple(_range(key, v) for v in value)
            else:
                ranges[key] = _range(key, value)
        return cls(ranges)

    def outside(self, spec: AirframeSpec) -> list[str]:
        """Each scale of `spec` outside the envelope, as words ("top rotor speed 2,600 rad/s")."""
        found = []
        for key, (words, unit) in SCALES.items():
            if key not in self.ranges:
                continue
            r, value = self.ranges[key], spec.scale(key)
            if isinstance(value, tuple):
                axes = [i for i, (v, ri) in enumerate(zip(value, r, strict=True))
                        if not _inside(v, ri)]  # type: ignore[arg-type]
                if axes:
                    found.append(f"{'/'.join(AXES[i] for i in axes)} {words} "
                                 f"{'/'.join(_number(value[i]) for i in axes)}{unit}")
            elif not _inside(value, r):  # type: ignore[arg-type]
                found.append(f"{words} {_number(value)}{unit}")
        return found

    def describe(self, keys: tuple[str, ...] = ("thrust_to_weight", "max_rotor_speed")) -> str:
        """In words, `keys` first: "thrust-to-weight 1.5–2.5, top rotor speed 750–1,250 rad/s"."""
        parts = []
        for key in keys:
            if key not in self.ranges:
                continue
            words, unit = SCALES[key]
            r = self.ranges[key]
            if isinstance(r[0], tuple):
                parts.append(f"{words} {', '.join(_span(x) for x in r)}{unit}")  # type: ignore[arg-type]
            else:
                parts.append(f"{words} {_span(r)}{unit}")  # type: ignore[arg-type]
        return ", ".join(parts)


def _range(key: str, value: object) -> Range:
    if (not isinstance(value, list) or len(value) != 2
            or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                       for v in value)
            or not 0.0 <= value[0] <= value[1]):
        raise ValueError(f"{key} {str(value)[:40]} is not a range [lo, hi] with 0 <= lo <= hi")
    return (float(value[0]), float(value[1]))


def _inside(value: float, r: Range) -> bool:
    return r[0] * (1.0 - ENVELOPE_SLACK) <= value <= r[1] * (1.0 + ENVELOPE_SLACK)


def _number(value: float) -> str:
    return f"{value:,.0f}" if abs(value) >= 100.0 else f"{value:.3g}"


def _span(r: Range) -> str:
    lo, hi = _number(r[0]), _number(r[1])
    return lo if lo == hi else f"{lo}–{hi}"
