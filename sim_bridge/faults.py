"""Faults injected where a real one acts: the gyro's reading, the ESC telemetry, the motors' thrust,
the battery's voltage. Pure Python and numpy; the twin applies a `FaultInjector` in its step
(sim_bridge/twin.py), so every controller meets the same fault.

A `Fault` names its target, its kind and the kind's parameter:

- gyro and esc-telemetry (sensing): `off` (no sample: NaN), `stuck` (the reading at injection,
  held), `garbage` (uniform noise over the sensor's range every tick), `wrong` (gyro: an offset
  of `value` rad/s on each axis, default 0.5; ESC telemetry: `value` × the speed, default 0.8),
  `slow` (a new sample every `value` s, default 0.01, held between), `delayed` (by `value` s,
  default 0.005), `intermittent` (each sample missing with probability `value`, default 0.2),
  `burst` (samples missing in bursts: a Gilbert–Elliott channel whose bursts last `burst_s` on
  average, default 0.02, losing `value` of all samples in the long run, default 0.01), `spikes`
  (each sample replaced by garbage with probability `value`, default 0.01);
- motor (actuation): `off` (the ESC stops driving the motor: its speed command is zero, so the
  rotor spins down and its telemetry says so) and `thrust` (the rotor makes `value` × its thrust,
  default 0.7: a damaged propeller, which the ESC telemetry cannot see);
- battery: `wrong` (the pack gives `value` × its voltage, default 0.75: one cell of four lost;
  the ESCs' speed command scales with it) and `off` (no voltage: every motor stops);
- payload: `mass` (a load of `value` × the airframe's mass, default 0.3, picked up at its centre and
  spread as its own mass is, so every moment of inertia grows by the same share: what the rate loop
  feels of a payload; the collective the outer loop asks for is unchanged).

Every sample carries the time it was taken, as a real bus delivers it: a missing one
(`intermittent`, `burst`, between `slow`'s samples) leaves the last sample with its old time, a
`delayed` one arrives late with its true time, `off` delivers NaN with the last sample's time;
`stuck`, `garbage`, `wrong` and `spikes` arrive on time (the sensor itself is wrong).

`instance` picks a motor (1..4, Betaflight order) for esc-telemetry and motor; 0 means all.
MAVLink's MAV_CMD_INJECT_FAILURE maps onto these in `from_mavlink` (documented there).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

GYRO_RANGE = math.radians(2000.0)  # rad/s: a MEMS gyro's full scale
ROTOR_SPEED_RANGE = 1.2  # × the airframe's top rotor speed: what garbage telemetry may read
SENSOR_KINDS = ("off", "stuck", "garbage", "wrong", "slow", "delayed", "intermittent", "burst", "spikes")
KINDS: dict[str, tuple[str, ...]] = {
    "gyro": SENSOR_KINDS,
    "esc-telemetry": SENSOR_KINDS,
    "motor": ("off", "thrust"),
    "battery": ("off", "wrong"),
    "payload": ("mass",),
}
_DEFAULTS = {("gyro", "wrong"): 0.5, ("esc-telemetry", "wrong"): 0.8, "slow": 0.01, "delayed": 0.005,
             "intermittent": 0.2, "burst": 0.01, "spikes": 0.01, "thrust": 0.7, ("battery", "wrong"): 0.75,
             "mass": 0.3}
BURST_S = 0.02  # a burst's mean length when none is given
MAX_PAYLOAD = 3.0  # × the airframe's mass: past this no quad lifts it
_UNITS = {"slow": "s", "delayed": "s", ("gyro", "wrong"): "rad/s"}

# MAVLink FAILURE_UNIT and FAILURE_TYPE values (common.xml).
UNIT_GYRO, UNIT_BATTERY, UNIT_MOTOR, UNIT_MAVLINK_SIGNAL = 0, 100, 101, 105
TYPE_NAMES = ("ok", "off", "stuck", "garbage", "wrong", "slow", "delayed", "intermittent")


class FaultSpecError(ValueError):
    """A fault that names no fault this twin can inject."""


@dataclass(frozen=True)
class Fault:
    target: str  # one of KINDS
    kind: str
    instance: int = 0  # 0: all; 1..4: motor (esc-telemetry, motor)
    value: float | None = None  # the kind's parameter; None: its default
    burst_s: float | None = None  # burst: the bursts' mean length in s; None: BURST_S

    def __post_init__(self) -> None:
        kinds = KINDS.get(self.target)
        if kinds is None:
            raise FaultSpecError(f"unknown fault target {self.target!r}: use {', '.join(KINDS)}")
        if self.kind not in kinds:
            raise FaultSpecError(f"{self.target} has no fault {self.kind!r}: use {', '.join(kinds)}")
        if not 0 <= self.instance <= (4 if self.target in ("esc-telemetry", "motor") else 1):
            raise FaultSpecError(f"{self.target}: no instance {self.instance}")
        v = self.value
        if v is not None and not math.isfinite(v):
            raise FaultSpecError(f"{self.describe()}: the value must be finite")
        if self.burst_s is not None and self.kind != "burst":
            raise FaultSpecError(f"{self.describe()}: only a burst has a length")
        b = self.burst_s
        if b is not None and not (math.isfinite(b) and 0.0 < b <= 1.0):
            raise FaultSpecError(f"{self.target} burst: a mean length of {b:g} s outside (0, 1] s")
        if v is not None and self.kind == "burst" and not 0.0 <= v < 1.0:
            raise FaultSpecError(f"{self.describe()}: {v:g} is not a fraction in [0, 1)")
        if v is not None and self.kind in ("intermittent", "spikes", "thrust") and not 0.0 <= v <= 1.0:
            raise FaultSpecError(f"{self.describe()}: {v:g} is not a fraction in [0, 1]")
        if v is not None and self.kind in ("slow", "delayed") and not 0.0 <= v <= 1.0:
            raise FaultSpecError(f"{self.describe()}: {v:g} s outside [0, 1] s")
        if v is not None and self.target == "battery" and not 0.0 <= v <= 1.0:
            raise FaultSpecError(f"{self.describe()}: {v:g} is not a fraction in [0, 1]")
        if v is not None and self.target == "payload" and not 0.0 <= v <= MAX_PAYLOAD:
            raise FaultSpecError(f"{self.describe()}: {v:g} × the mass is outside [0, {MAX_PAYLOAD:g}]")

    @property
    def parameter(self) -> float:
        if self.value is not None:
            return self.value
        return float(_DEFAULTS.get((self.target, self.kind), _DEFAULTS.get(self.kind, 0.0)))

    @property
    def burst_length(self) -> float:
        return BURST_S if self.burst_s is None else self.burst_s

    def describe(self) -> str:
        """For a STATUSTEXT and a table: 'motor 2 thrust 0.7', 'esc-telemetry delayed 0.005 s'."""
        who = self.target if not self.instance else f"{self.target} {self.instance}"
        if self.kind == "burst":
            return f"{who} burst {self.burst_length:g} s @ {self.parameter:g}"
        if (self.target, self.kind) not in _DEFAULTS and self.kind not in _DEFAULTS:
            return f"{who} {self.kind}"
        unit = _UNITS.get((self.target, self.kind), _UNITS.get(self.kind, ""))
        return f"{who} {self.kind} {self.parameter:g}{' ' + unit if unit else ''}"


def from_mavlink(unit: int, failure_type: int, instance: int) -> list[Fault] | str:
    """MAV_CMD_INJECT_FAILURE's (param1, param2, param3) as faults ([] for FAILURE_TYPE_OK: clear),
    or why it is unsupported.

    SENSOR_GYRO: every type. SYSTEM_MOTOR: OFF and WRONG act on what the motor produces (off; WRONG
    = 70 % thrust); STUCK, GARBAGE, SLOW, DELAYED, INTERMITTENT act on what it reports, its ESC
    telemetry (MAVLink has no ESC-telemetry unit; the telemetry is the motor's own sensor, so the
    data-quality types go to it). SYSTEM_BATTERY: OFF, WRONG (75 % voltage). The MAVLink signal is
    the MAVLink process's, not the twin's (firmware/mavlink/handlers.py).
    """
    if not 0 <= failure_type < len(TYPE_NAMES):
        return f"failure type {failure_type} unknown"
    name = TYPE_NAMES[failure_type]
    target = {UNIT_GYRO: "gyro", UNIT_MOTOR: "motor", UNIT_BATTERY: "battery"}.get(unit)
    if target is None:
        return f"failure unit {unit} not simulated"
    if name == "ok":
        return []
    if target == "motor":
        target, name = ("motor", {"off": "off", "wrong": "thrust"}[name]) if name in ("off", "wrong") \
            else ("esc-telemetry", name)
    if name not in KINDS[target]:
        return f"{target} {name} not simulated"
    try:
        return [Fault(target, name, instance)]
    except FaultSpecError as exc:
        return str(exc)


class _SensorFault:
    """One fault on some columns of a reading and their sample times, with its state (held sample,
    delay line, burst state, clock)."""

    def __init__(self, fault: Fault, columns: list[int], span: tuple[float, float], dt: float) -> None:
        self.fault, self.kind, self.columns, self.span = fault, fault.kind, columns, span
        self.p = fault.parameter
        self.every = max(1, round(self.p / dt)) if fault.kind == "slow" else 1
        self.delay = max(0, round(self.p / dt)) if fault.kind == "delayed" else 0
        # Gilbert–Elliott: a burst ends with probability `leave` a sample, one starts with `enter`,
        # so a burst lasts burst_s on average and the channel loses p of all samples in the long run.
        self.leave = min(1.0, dt / fault.burst_length)
        self.enter = self.leave * self.p / (1.0 - self.p) if fault.kind == "burst" else 0.0
        self.in_burst = False
        self.held: tuple[list[float], list[int]] | None = None  # a sample and its times
        self.line: deque[tuple[list[float], list[int]]] = deque()
        self.n = 0

    def apply(self, values: list[float], times: list[int], rng: np.random.Generator) -> None:
        cols, kind = self.columns, self.kind
        mine = [values[c] for c in cols]
        now = [times[c] for c in cols]
        out, out_t = mine, now
        held = self.held
        if kind == "off":
            if held is None:
                held = self.held = (mine, now)
            out, out_t = [math.nan] * len(cols), held[1]
        elif kind == "stuck":
            if held is None:
                held = self.held = (mine, now)
            out = held[0]
        elif kind == "garbage" or (kind == "spikes" and rng.random() < self.p):
            out = rng.uniform(*self.span, len(cols)).tolist()
        elif kind == "wrong":
            out = [v + self.p for v in mine] if self.fault.target == "gyro" else [v * self.p for v in mine]
        elif kind == "slow":
            if self.n % self.every == 0 or held is None:
                held = self.held = (mine, now)
            out, out_t = held
        elif kind == "delayed":
            if not self.line:
                self.line.extend([(mine, now)] * self.delay)
            self.line.append((mine, now))
            out, out_t = self.line.popleft()
        elif kind in ("intermittent", "burst"):
            if kind == "burst":
                self.in_burst = rng.random() >= self.leave if self.in_burst else rng.random() < self.enter
                lost = self.in_burst
            else:
                lost = rng.random() < self.p
            if lost and held is not None:
                out, out_t = held
            else:
                self.held = (mine, now)
        self.n += 1
        for c, v, t in zip(cols, out, out_t, strict=True):
            values[c] = v
            times[c] = t


class FaultInjector:
    """The faults active on one twin, applied in the order injected.

    `dt`: the twin's step; `max_rotor_speed`: the range of garbage telemetry; `seed`: the random
    draws of garbage, spikes and intermittent samples (a stream of their own).
    """

    def __init__(self, dt: float, max_rotor_speed: float, seed: int | None = None) -> None:
        self.dt = dt
        self.max_rotor_speed = max_rotor_speed
        self.rng = np.random.default_rng(seed)
        self.faults: list[Fault] = []
        self._sensing: list[_SensorFault] = []
        self._command_off = [False] * 4
        self.thrust_scale: list[float] | None = None
        self.speed_scale: float | None = None
        self.payload: float | None = None  # the load carried, × the airframe's mass

    def __bool__(self) -> bool:
        return bool(self.faults)

    def inject(self, fault: Fault) -> None:
        """Add `fault`; one on the same target and instance replaces it."""
        self.faults = [f for f in self.faults if (f.target, f.instance) != (fault.target, fault.instance)]
        self.faults.append(fault)
        self._rebuild()

    def clear(self, target: str | None = None, instance: int = 0) -> None:
        """Remove the faults on `target` (all targets if None), of `instance` (0: every instance)."""
        self.faults = [f for f in self.faults if target is not None and (
            f.target != target or (instance and f.instance != instance))]
        self._rebuild()

    def _rebuild(self) -> None:
        kept = {id(s.fault): s for s in self._sensing}
        self._sensing = []
        self._command_off = [False] * 4
        thrust, speed, payload = [1.0] * 4, 1.0, 0.0
        for f in self.faults:
            motors = range(4) if f.instance == 0 else [f.instance - 1]
            if f.target == "gyro":
                self._sensing.append(kept.get(id(f)) or _SensorFault(f, [0, 1, 2], (-GYRO_RANGE, GYRO_RANGE),
                                                                     self.dt))
            elif f.target == "esc-telemetry":
                span = (0.0, ROTOR_SPEED_RANGE * self.max_rotor_speed)
                columns = [3 + m for m in motors]
                self._sensing.append(kept.get(id(f)) or _SensorFault(f, columns, span, self.dt))
            elif f.target == "motor":
                for m in motors:
                    if f.kind == "off":
                        self._command_off[m] = True
                    else:
                        thrust[m] *= f.parameter
            elif f.target == "battery":
                speed *= 0.0 if f.kind == "off" else f.parameter
            elif f.target == "payload":
                payload += f.parameter
        self.thrust_scale = thrust if thrust != [1.0] * 4 else None
        self.speed_scale = speed if speed != 1.0 else None
        self.payload = payload or None

    # ---- actuation: where PWM becomes a speed command, and speed becomes thrust ----
    def motor_command(self, pwm: list[float], pwm_min: float) -> list[float]:
        off = self._command_off
        return [pwm_min if off[i] else pwm[i] for i in range(4)]

    def thrust(self, thrust: list[float]) -> list[float]:
        scale = self.thrust_scale
        return thrust if scale is None else [t * s for t, s in zip(thrust, scale, strict=True)]

    # ---- sensing: what the gyro and the ESC telemetry report ----
    def read(self, gyro: np.ndarray, rotor_speed: np.ndarray, t_us: int
             ) -> tuple[np.ndarray, np.ndarray, int | None, np.ndarray | None]:
        """What the sensors report at `t_us`: (gyro, rotor speed, the gyro's sample time, each
        motor's); the times are None while no sensing fault is active (sampled at `t_us`)."""
        if not self._sensing:
            return gyro, rotor_speed, None, None
        values = gyro.tolist() + rotor_speed.tolist()
        times = [t_us] * 7
        for s in self._sensing:
            s.apply(values, times, self.rng)
        return np.array(values[:3]), np.array(values[3:]), times[0], np.array(times[3:], dtype=np.int64)


def mavlink_injector(twin, seed: int | None = None):
    """MAV_CMD_INJECT_FAILURE's (unit, type, instance) → (accepted, text), acting on `twin`
    (a `sim_bridge.twin.Twin`), whose `faults` it creates on first use."""

    def inject(unit: int, failure_type: int, instance: int) -> tuple[bool, str]:
        faults = from_mavlink(unit, failure_type, instance)
        if isinstance(faults, str):
            return False, faults
        if twin.faults is None:
            twin.faults = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, seed)
        if not faults:
            target = {UNIT_GYRO: "gyro", UNIT_BATTERY: "battery"}.get(unit)
            if target is None:  # the motor: what it produces and what it reports
                twin.faults.clear("motor", instance)
                twin.faults.clear("esc-telemetry", instance)
            else:
                twin.faults.clear(target, instance)
            return True, f"unit {unit}{f' {instance}' if instance else ''} ok"
        for fault in faults:
            twin.faults.inject(fault)
        return True, ", ".join(f.describe() for f in faults)

    return inject
