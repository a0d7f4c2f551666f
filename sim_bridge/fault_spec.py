"""Faults named on a command line (`fcemu eval --fault`, `fcemu bench loop --fault`, `fcemu twin serve
--fault`), and the injector a twin server's session starts with.

A SPEC is `TARGET:KIND[:VALUE]` with an optional motor number anywhere after the target, e.g.
`gyro:stuck`, `esc-telemetry:delayed:5ms`, `esc-telemetry:3:stuck`, `motor:2:thrust=0.7`,
`battery:wrong=0.75` (sim_bridge/faults.py lists the kinds and their defaults). VALUE takes `ms`,
`s`, `Hz` (a period) or `%`. A burst's VALUE is `LENGTH@FRACTION`: `esc-telemetry:burst:20ms@1%`
(`burst:20ms` and `burst:1%`, one of the two, keep the other's default).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from fcemu.sim_bridge.faults import Fault, FaultInjector, FaultSpecError
from fcemu.sim_bridge.twin import Twin

SESSION_STREAM = 0x6661756C  # "faul": a session's fault draws, a stream apart from the twin's noise
_VALUE = re.compile(r"^([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)(ms|s|hz|%)?$", re.IGNORECASE)


def parse_value(text: str) -> float:
    m = _VALUE.match(text.strip())
    if m is None:
        raise FaultSpecError(f"{text!r} is not a number (units: ms, s, Hz, %)")
    value, unit = float(m.group(1)), (m.group(2) or "").lower()
    if unit == "hz":
        if value <= 0:
            raise FaultSpecError(f"{text!r}: a rate must be positive")
        return 1.0 / value
    return value * {"ms": 1e-3, "%": 1e-2}.get(unit, 1.0)


def parse_fault(spec: str) -> Fault:
    """A --fault SPEC as a `Fault`; FaultSpecError (a ValueError) says what is wrong with it."""
    parts = spec.split(":")
    target, instance, kind, raw = parts[0], 0, None, None
    try:
        for part in parts[1:]:
            if part.isdigit() and not instance:
                instance = int(part)
            elif "=" in part and kind is None:
                kind, _, raw = part.partition("=")
            elif kind is None and part:
                kind = part
            elif raw is None and part:
                raw = part
            else:
                raise FaultSpecError(f"unexpected {part!r}")
        if kind is None:
            raise FaultSpecError("no fault kind: use TARGET:KIND[:VALUE], e.g. gyro:stuck")
        if kind == "burst" and raw is not None:
            return Fault(target, kind, instance, *_burst_values(raw))
        return Fault(target, kind, instance, None if raw is None else parse_value(raw))
    except FaultSpecError as exc:
        raise FaultSpecError(f"--fault {spec!r}: {exc}") from None


def _burst_values(raw: str) -> tuple[float | None, float | None]:
    """`LENGTH@FRACTION`, `LENGTH` (with a time unit) or `FRACTION` as (fraction, length in s)."""
    length, at, fraction = raw.partition("@")
    if not at:
        timed = raw.strip().lower().endswith(("ms", "s", "hz"))
        length, fraction = (raw, "") if timed else ("", raw)
    return (parse_value(fraction) if fraction else None, parse_value(length) if length else None)


def session_faults(twin: Twin, faults: Sequence[Fault], seed: int | None) -> FaultInjector | None:
    """`faults` as they start with a session that RESET with `seed`: their random draws (intermittent,
    burst, garbage, spikes) seeded by it on a stream of their own (None: fresh); None for no faults.
    ValueError for a negative seed (the twin refuses one too)."""
    if not faults:
        return None
    stream = None if seed is None else int(
        np.random.SeedSequence(seed, spawn_key=(SESSION_STREAM,)).generate_state(1)[0])
    injector = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, stream)
    for fault in faults:
        injector.inject(fault)
    return injector
