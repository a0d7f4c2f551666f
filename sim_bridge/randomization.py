"""Domain-randomisation ranges: one data file beside the airframe, loaded and validated here.

`airframes/<name>.randomization.json` gives, per parameter, its unit, nominal value (the
airframe file's), range [lo, hi] and a source or justification. Every parameter is drawn
independently, in `PARAMETERS` order. `Randomization.draw` returns one airframe as
`Airframe.scaled` keywords, so an environment or the evaluator builds it with
`base.scaled(**draw)`:

- mass, inertia and motor constants ("scale"): drawn from U[lo, hi], given as the factor
  value / nominal; lo <= nominal <= hi.
- the airframe's effects ("value", `sim_bridge.plant`): drawn from U[lo, hi], given as the
  value itself. The nominal twin has most effects off (0), so the range need not hold the
  nominal (e.g. battery resistance); per-axis effects give a 3-tuple, None where not drawn.
- latencies in whole ticks ("ticks"): an integer drawn uniformly from lo..hi inclusive.

A parameter becomes randomisable when the twin honours it: add its row to `PARAMETERS`
(where its nominal lives in the airframe, which `scaled` keyword it sets, how it is drawn)
and its range to the file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.sim_bridge.airframe import AIRFRAME_DIR, DEFAULT_AIRFRAME, Airframe, load_airframe
from fcemu.sim_bridge.randomization_parameters import (
    BUS_PARAMETERS,
    GYRO_KEYWORDS,
    PARAMETERS,
    Parameter,
    RandomizationError,
    known_parameters,
)
from fcemu.sim_bridge.relative_ranges import absolute_ranges, is_relative

SUFFIX = ".randomization.json"
RELATIVE = "relative"  # the shipped ranges relative to any airframe (sim_bridge.relative_ranges)
NOMINAL_RTOL = 1e-9
__all__ = [
    "BUS_PARAMETERS",
    "GYRO_KEYWORDS",
    "PARAMETERS",
    "RELATIVE",
    "SUFFIX",
    "Parameter",
    "ParameterRange",
    "Randomization",
    "RandomizationError",
    "known_parameters",
    "load_randomization",
    "parse_randomization",
    "randomization_path",
    "ranges_for",
]


@dataclass(frozen=True)
class ParameterRange:
    key: str
    unit: str
    nominal: float
    lo: float
    hi: float
    source: str


@dataclass(frozen=True)
class Randomization:
    """Validated ranges for one airframe; parameters in the file's order, drawn in `PARAMETERS` order.

    Iterating gives the `Airframe.scaled` keywords a draw sets, as iterating the
    environments' ± fraction mapping gives its keys.
    """

    airframe: str
    parameters: tuple[ParameterRange, ...]
    path: Path | None = None
    base: Airframe | None = field(default=None, compare=False)  # the airframe, where the caller gave it

    def __iter__(self) -> Iterator[str]:
        return iter(dict.fromkeys(PARAMETERS[p.key].keyword for p in self._ordered()))

    def __len__(self) -> int:
        return len(self.parameters)

    def parameter(self, key: str) -> ParameterRange:
        """The range of file key `key` (e.g. "inertia_xx")."""
        for p in self.parameters:
            if p.key == key:
                return p
        raise KeyError(f"no range for {key!r}; the file has {[p.key for p in self.parameters]}")

    def _ordered(self) -> list[ParameterRange]:
        order = list(PARAMETERS)
        return sorted(self.parameters, key=lambda p: order.index(p.key))

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        """One airframe as `Airframe.scaled` keywords: factors of mass, inertia and motor constants
        (per-axis: a 3-tuple, 1.0 where not drawn), effect values (per-axis: None where not drawn)."""
        def drawn(p: ParameterRange, kind: str) -> Any:
            if kind == "ticks":
                return int(rng.integers(round(p.lo), round(p.hi) + 1))
            value = float(rng.uniform(p.lo, p.hi))
            return value / p.nominal if kind == "scale" else value

        return self._keywords(drawn)

    def nominal(self) -> dict[str, Any]:
        """The airframe the ranges are for, as the keywords a draw sets (so an episode that flies
        it replaces a drawn airframe in every parameter a draw could have changed)."""
        return self._keywords(lambda p, kind: 1.0 if kind == "scale" else round(p.nominal) if kind == "ticks"
                              else p.nominal)

    def _keywords(self, value_of: Callable[[ParameterRange, str], Any]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for p in self._ordered():
            _, keyword, axis, kind = PARAMETERS[p.key]
            value = value_of(p, kind)
            if axis is None:
                out[keyword] = value
            else:
                axes = list(out.get(keyword, (1.0, 1.0, 1.0) if kind == "scale" else (None, None, None)))
                axes[axis] = value
                out[keyword] = tuple(axes)
        return out

    @property
    def draws_gyro_noise(self) -> bool:
        return any(PARAMETERS[p.key].keyword == "gyro_noise_std" for p in self.parameters)

    @property
    def draws_gyro_effects(self) -> bool:
        """Whether a drawn airframe's gyro may read other than the rate (noise, vibration, delay)."""
        return any(PARAMETERS[p.key].keyword in GYRO_KEYWORDS for p in self.parameters)

    def base_airframe(self) -> Airframe:
        """The airframe the ranges are for: the one they were built for or checked against, else the
        file beside them, else the shipped one by name."""
        if self.base is not None:
            return self.base
        sibling = None if self.path is None else self.path.parent / f"{self.airframe}.json"
        try:
            return load_airframe(sibling if sibling is not None and sibling.exists() else self.airframe)
        except (OSError, ValueError, KeyError) as exc:
            raise RandomizationError(f"{self.path or 'ranges'}: cannot load airframe {self.airframe!r}: "
                                     f"{exc}") from None

    def check_airframe(self, airframe: Airframe) -> None:
        """Raise unless every nominal value is the airframe's own."""
        where = self.path or self.airframe
        if airframe.name != self.airframe:
            raise RandomizationError(f"{where}: ranges are for airframe {self.airframe!r}, "
                                     f"not {airframe.name!r}")
        for p in self.parameters:
            actual = PARAMETERS[p.key].nominal(airframe)
            if not math.isclose(p.nominal, actual, rel_tol=NOMINAL_RTOL):
                raise RandomizationError(f"{where}: {p.key} nominal {p.nominal:g} is not the airframe's "
                                         f"{actual:g}")


def randomization_path(name_or_path: str | Path) -> Path:
    """`iris` -> the shipped `airframes/iris.randomization.json`; anything with a suffix is a path."""
    path = Path(name_or_path)
    return path if path.suffix else AIRFRAME_DIR / f"{name_or_path}{SUFFIX}"


def load_randomization(name_or_path: str | Path = DEFAULT_AIRFRAME,
                       airframe: Airframe | None = None) -> Randomization:
    """Read, validate and check against its airframe; every problem is a `RandomizationError`.

    Ranges relative to the airframe (`relative`) need `airframe` and are built for it; absolute
    ones are checked against it where it is given.
    """
    path = randomization_path(name_or_path)
    if not path.exists():
        known = ", ".join(sorted(p.name[: -len(SUFFIX)] for p in AIRFRAME_DIR.glob(f"*{SUFFIX}")))
        raise RandomizationError(f"no randomisation file {path} (shipped: {known})")
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RandomizationError(f"{path}: cannot read as JSON: {exc}") from None
    if is_relative(raw):
        if airframe is None:
            raise RandomizationError(f"{path}: the ranges are relative to the airframe they are applied to: "
                                     f"load them for one (ranges_for(airframe, {str(name_or_path)!r}))")
        raw = absolute_ranges(raw, airframe, where=str(path))
    ranges = parse_randomization(raw, where=str(path))
    ranges = Randomization(ranges.airframe, ranges.parameters, path, airframe)
    ranges.check_airframe(ranges.base_airframe())
    return ranges


def ranges_for(airframe: Airframe | str | Path, name_or_path: str | Path | None = None) -> Randomization:
    """The randomisation ranges of `airframe` (an Airframe, a shipped name or a file).

    `name_or_path` None: the airframe's own shipped `<name>.randomization.json` where there is one
    (the Iris's), else the ranges relative to any airframe (`relative`) built for this one. Named
    ranges: relative ones are built for the airframe, absolute ones must be the airframe's.
    """
    if not isinstance(airframe, Airframe):
        try:
            airframe = load_airframe(airframe)
        except FileNotFoundError as exc:
            raise RandomizationError(str(exc)) from None
    if name_or_path is None:
        own = AIRFRAME_DIR / f"{airframe.name}{SUFFIX}"
        name_or_path = own if own.exists() else RELATIVE
    return load_randomization(name_or_path, airframe)


def parse_randomization(raw: Any, where: str = "ranges") -> Randomization:
    """Validate the file's JSON object: known keys, finite numbers (positive, lo <= nominal <= hi for
    scale factors; >= 0 for effects; whole for ticks), lo <= hi, a source."""
    if not isinstance(raw, dict):
        raise RandomizationError(f"{where}: expected a JSON object, got {type(raw).__name__}")
    airframe = raw.get("airframe")
    if not isinstance(airframe, str) or not airframe:
        raise RandomizationError(f"{where}: \"airframe\" must name the airframe file the ranges are for")
    params = known_parameters(raw, where)
    ranges = Randomization(airframe, tuple(_parameter(key, entry, where) for key, entry in params.items()))
    _check_inertia(ranges, where)
    return ranges


def _check_inertia(ranges: Randomization, where: str) -> None:
    """Every draw must be a rigid body: each principal inertia at most the sum of the other two."""
    axes = ("inertia_xx", "inertia_yy", "inertia_zz")
    bounds = {}
    for key in axes:
        try:
            p = ranges.parameter(key)
            bounds[key] = (p.lo, p.hi)
        except KeyError:
            continue
    if len(bounds) < 3:
        return  # checked when the file draws all three axes
    for key in axes:
        others = [bounds[k][0] for k in axes if k != key]
        if bounds[key][1] > sum(others):
            raise RandomizationError(f"{where}: {key} up to {bounds[key][1]:g} exceeds the other two axes' "
                                     f"lowest sum {sum(others):g}: such a draw is no rigid body "
                                     f"(I_i <= I_j + I_k)")


def _parameter(key: str, entry: Any, where: str) -> ParameterRange:
    at = f"{where}: {key}"
    if not isinstance(entry, dict):
        raise RandomizationError(f"{at}: expected an object with nominal, range, unit and source")
    missing = sorted({"nominal", "range", "unit", "source"} - set(entry))
    if missing:
        raise RandomizationError(f"{at}: missing {missing}")
    rng = entry["range"]
    if not isinstance(rng, list) or len(rng) != 2:
        raise RandomizationError(f"{at}: range must be [lo, hi], got {rng!r}")
    kind = PARAMETERS[key].kind
    values = (entry["nominal"], *rng)
    finite = all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in values)
    if kind == "scale" and not (finite and min(values) > 0):
        raise RandomizationError(f"{at}: nominal and range must be finite positive numbers, got "
                                 f"nominal {entry['nominal']!r}, range {rng!r}")
    if kind != "scale" and not (finite and min(values) >= 0):
        raise RandomizationError(f"{at}: an effect's nominal and range must be finite numbers >= 0, got "
                                 f"nominal {entry['nominal']!r}, range {rng!r}")
    nominal, lo, hi = (float(v) for v in values)
    if kind == "scale" and not lo <= nominal <= hi:
        raise RandomizationError(f"{at}: need lo <= nominal <= hi, got {lo:g} <= {nominal:g} <= {hi:g}")
    if not lo <= hi:
        raise RandomizationError(f"{at}: need lo <= hi, got [{lo:g}, {hi:g}]")
    if key == "esc_telemetry_loss" and hi >= 1.0:
        raise RandomizationError(f"{at}: a share of frames lost must stay below 1, got range {rng!r}")
    if kind == "ticks" and not all(float(v).is_integer() for v in values):
        raise RandomizationError(f"{at}: ticks must be whole numbers, got nominal {entry['nominal']!r}, "
                                 f"range {rng!r}")
    source = entry["source"]
    if not isinstance(source, str) or not source.strip():
        raise RandomizationError(f"{at}: source must say where the range comes from")
    if not isinstance(entry["unit"], str):
        raise RandomizationError(f"{at}: unit must be a string")
    return ParameterRange(key, entry["unit"], nominal, lo, hi, source)
