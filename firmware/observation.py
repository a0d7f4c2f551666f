"""The neural controller's observation: one definition for training, flight and export.

The GymFC observation (Koch et al. 2018): the rate error e = Ω* − Ω (3) and the rotor
speeds (4) for the last `memory` steps, newest first. Optional field
`rate_error_integral` (3): a leaky integral of the scaled rate error,
I_k = λ·I_{k−1} + (1 − λ)·e_k with I = (1 − λ)·e_0 at the episode start; a policy with
m = 1 has no other memory, so it cannot remove a steady offset the way a PID's I term
does. Optional field `rate_error_rms` (3): the leaky root-mean-square of the scaled rate
error, R_k = √P_k with P_k = μ·P_{k−1} + (1 − μ)·e_k², over about one period of the
limit cycles a fast policy can fall into on a slow airframe (17–60 Hz): a 16 ms history
sees less than a period, and the integral averages an oscillation to zero; a policy trained
with it softens its steps instead of oscillating. Optional field `rate` (3): the gyro's body
rates Ω themselves, scaled as the error; the error alone hides where the rates are, and so
the body's gyroscopic torque Ω × IΩ.
Optional field `loop_delay` (1): the loop's delay in ticks beyond the sample's own (the ESC
protocol's and the gyro filters' delays a flight controller is configured with; `AirframeSpec.
loop_delay_ticks`), times `loop_delay_scale`: the same in every step of a flight, it is what lets one
network lower its gain where the loop is long, which a 16-step history does not show.
Optional field `authority` (3): per axis, the angular acceleration the quad gives per unit of
its torque command, estimated in flight from its own gyro and ESC telemetry: the leaky
least-squares slope of the gyro's change per tick, y, on the mixer's differential of the rotors'
thrust shares, x = Σ_i T_ia·(ω_i/ω_top)² (`mixer.BETAFLIGHT_QUAD_X`), each centred on its leaky
mean, cov(x, y) / (var(x) + ε), times `authority_scale` (0 until the motors have moved). What a
policy flying any quad must learn of the one it flies, and what changes with a payload or a weak
motor; a short history shows it only while the motors move within it.
Optional field `motor_output` (4): the motor outputs u = (PWM − 1000) / 1000 the
controller commanded on the previous tick. A penalty on |Δu| in the reward depends on them,
and the rotor speeds show them only through the motors' lag; at a start there is no previous tick, and u is
taken as the steady-state command of the rotors' speeds, clip(ω · rotor_speed_scale, 0, 1)
(exact for an airframe whose speed is linear in u up to its top speed). The spec
travels in the model's metadata and the firmware refuses a model whose spec differs.

`FIELD_DEFS` declares each field (its source signal, the spec's scale for it, whether it
is integrated); `ObservationSpec.columns` gives each field's columns by name, and
`column_sources`/`column_scales` flatten it per column; `observe_step` and
`ObservationHistory` compute from that, and a generator of C code can read the same table.
One formula serves one vehicle (plain floats, written into a preallocated batch of one:
numpy's per-call overhead on 3-vectors would cost more than the model) and a batch (arrays
with any leading shape), with the same IEEE operations.
"""

from __future__ import annotations

import json
from dataclasses import InitVar, asdict, dataclass, replace
from functools import cached_property
from operator import itemgetter, mul

import numpy as np

OBS_VERSION = 1
DEFAULT_LEAK = 0.995  # λ per step: τ = 200 steps (0.2 s at 1 kHz)
DEFAULT_RMS_LEAK = 0.98  # μ per step: τ = 50 steps, one period at 20 Hz
DEFAULT_LOOP_DELAY_SCALE = 0.2  # ticks -> 0..1 over the 0-5 ticks of the randomisation ranges
RATE_ERROR = "rate_error"
ROTOR_SPEED = "rotor_speed"
FIELDS = (RATE_ERROR, ROTOR_SPEED)  # the default; the shipped policy's spec
INTEGRAL = "rate_error_integral"
RMS = "rate_error_rms"
MOTOR_OUTPUT = "motor_output"
RATE = "rate"
LOOP_DELAY = "loop_delay"
AUTHORITY = "authority"
# The signals a field can read, as columns of one source vector: the rate error
# setpoint − gyro (rad/s, FRD), the rotor speeds (rad/s, motor order), the gyro (rad/s,
# FRD), the previous tick's motor outputs (0..1, motor order), the loop's configured delay (ticks).
SOURCE_COLUMNS = {"rate_error": (0, 1, 2), "rotor_speed": (3, 4, 5, 6), "gyro": (7, 8, 9),
                  "motor_output": (10, 11, 12, 13), "loop_delay": (14,)}

_FLOAT64 = np.dtype(np.float64)


@dataclass(frozen=True)
class FieldDef:
    """One observation field: `source` times the spec's `scale` attribute (None: 1), float32.

    With `leak` (the name of the spec's λ attribute) the field is leaky-integrated over
    steps by `ObservationHistory`; with `rms` too, of its square, and stored as the root.
    """

    source: str
    scale: str | None
    leak: str | None = None
    rms: bool = False
    slope: bool = False  # the in-flight authority estimate of its source (the gyro): `ObservationHistory`

    @property
    def integrated(self) -> bool:
        return self.leak is not None

    @property
    def size(self) -> int:
        return len(SOURCE_COLUMNS[self.source])


FIELD_DEFS: dict[str, FieldDef] = {
    RATE_ERROR: FieldDef("rate_error", "rate_scale"),
    ROTOR_SPEED: FieldDef("rotor_speed", "rotor_speed_scale"),
    INTEGRAL: FieldDef("rate_error", "rate_scale", leak="integral_leak"),
    RMS: FieldDef("rate_error", "rate_scale", leak="rms_leak", rms=True),
    MOTOR_OUTPUT: FieldDef("motor_output", None),
    RATE: FieldDef("gyro", "rate_scale"),
    LOOP_DELAY: FieldDef("loop_delay", "loop_delay_scale"),
    AUTHORITY: FieldDef("gyro", "rate_scale", leak="authority_leak", slope=True),
}
LEAKS = frozenset(d.leak for d in FIELD_DEFS.values() if d.leak)  # the spec's λ attributes
# Spec attributes only some fields use: a spec serialises them only with their fields (older readers).
OPTIONAL_ATTRIBUTES = LEAKS | {"loop_delay_scale", "authority_scale"}
DEFAULT_AUTHORITY_LEAK = 0.998  # τ = 500 steps: several of the slowest motor lags' transients
# The slope in scaled rate per tick per share²: an Iris's roll about 0.02, a whoop's about 0.2.
DEFAULT_AUTHORITY_SCALE = 10.0
AUTHORITY_EPSILON = 1e-4  # share⁴: the variance of x under which the slope stays near 0 (motors still)


@dataclass(frozen=True)
class ObservationSpec:
    """`rotor_speed_scale` is 1 / the airframe's max rotor speed: give it, or `max_rotor_speed`."""

    memory: int = 1
    rate_scale: float = 1.0 / 5.24  # rad/s -> about ±1 at the paper's command bound
    rotor_speed_scale: float = None  # type: ignore[assignment]  # rad/s -> 0..1 at the airframe's top speed
    fields: tuple[str, ...] = FIELDS
    version: int = OBS_VERSION
    integral_leak: float = DEFAULT_LEAK  # only with INTEGRAL
    rms_leak: float = DEFAULT_RMS_LEAK  # only with RMS
    loop_delay_scale: float = DEFAULT_LOOP_DELAY_SCALE  # only with LOOP_DELAY
    authority_leak: float = DEFAULT_AUTHORITY_LEAK  # only with AUTHORITY
    authority_scale: float = DEFAULT_AUTHORITY_SCALE  # only with AUTHORITY
    # The rotor speeds as shares of the flown airframe's own top speed, whatever airframe that is: a
    # policy trained across many quads. rotor_speed_scale is then the trained airframe's, and the
    # firmware takes the flown one's (`for_airframe`).
    per_airframe_rotor_speed: bool = False
    max_rotor_speed: InitVar[float | None] = None  # rad/s: sets rotor_speed_scale = 1 / it

    def __post_init__(self, max_rotor_speed: float | None) -> None:
        if max_rotor_speed is not None:
            if self.rotor_speed_scale is not None:
                raise ValueError("give rotor_speed_scale or max_rotor_speed, not both")
            if not max_rotor_speed > 0:
                raise ValueError(f"max_rotor_speed must be > 0 rad/s, got {max_rotor_speed}")
            object.__setattr__(self, "rotor_speed_scale", 1.0 / max_rotor_speed)
        elif self.rotor_speed_scale is None:
            raise ValueError("an observation spec needs its airframe's top rotor speed: give max_rotor_speed "
                             "(rad/s) or rotor_speed_scale")
        if self.memory < 1:
            raise ValueError(f"memory must be >= 1, got {self.memory}")
        unknown = set(self.fields) - set(FIELD_DEFS)
        if unknown:
            raise ValueError(f"unknown observation fields {sorted(unknown)}")
        if len(set(self.fields)) != len(self.fields):
            raise ValueError(f"repeated observation fields {self.fields}")
        if AUTHORITY in self.fields and ROTOR_SPEED not in self.fields:
            raise ValueError("the authority field reads the rotor speeds: give rotor_speed too")
        for leak in LEAKS:
            if not 0.0 <= getattr(self, leak) < 1.0:
                raise ValueError(f"{leak} must be in [0, 1), got {getattr(self, leak)}")

    @property
    def step_size(self) -> int:
        return sum(FIELD_DEFS[f].size for f in self.fields)

    @property
    def size(self) -> int:
        return self.step_size * self.memory

    @cached_property
    def layout(self) -> tuple[tuple[slice, FieldDef, float], ...]:
        """Per field in order: its columns within one step, its definition, its scale."""
        out, start = [], 0
        for name in self.fields:
            d = FIELD_DEFS[name]
            scale = 1.0 if d.scale is None else float(getattr(self, d.scale))
            out.append((slice(start, start + d.size), d, scale))
            start += d.size
        return tuple(out)

    @cached_property
    def columns(self) -> dict[str, slice]:
        """Each field's columns within one step (the newest, the observation's first), by name."""
        return {name: cols for name, (cols, *_) in zip(self.fields, self.layout, strict=True)}

    @cached_property
    def column_sources(self) -> tuple[int, ...]:
        """Per column of one step: the source-vector column it reads."""
        return tuple(c for _, d, _ in self.layout for c in SOURCE_COLUMNS[d.source])

    @cached_property
    def column_scales(self) -> tuple[float, ...]:
        """Per column of one step: the scale its source is multiplied by."""
        return tuple(scale for _, d, scale in self.layout for _ in SOURCE_COLUMNS[d.source])

    @cached_property
    def _pick_sources(self) -> itemgetter:
        return itemgetter(*self.column_sources)

    @cached_property
    def reads_motor_output(self) -> bool:
        return any(d.source == "motor_output" for _, d, _ in self.layout)

    @cached_property
    def reads_loop_delay(self) -> bool:
        return LOOP_DELAY in self.fields

    @cached_property
    def integrators(self) -> tuple[tuple[slice, float, bool], ...]:
        """Per integrated field in order: its columns within one step, its λ, whether RMS."""
        return tuple((cols, float(getattr(self, d.leak)), d.rms) for cols, d, _ in self.layout
                     if d.leak and not d.slope)

    @cached_property
    def slope(self) -> tuple[slice, slice] | None:
        """The authority field's columns and the rotor speeds' (None: no such field)."""
        if AUTHORITY not in self.fields:
            return None
        return self.columns[AUTHORITY], self.columns[ROTOR_SPEED]

    def for_airframe(self, max_rotor_speed: float) -> ObservationSpec:
        """The spec as the firmware flies it on an airframe of this top rotor speed: its own scale where
        the rotor speeds are shares of the flown airframe's (`per_airframe_rotor_speed`), else itself."""
        if not self.per_airframe_rotor_speed:
            return self
        return replace(self, rotor_speed_scale=1.0 / max_rotor_speed)

    def to_json(self) -> str:
        raw = asdict(self)
        used = {a for f in self.fields for a in (FIELD_DEFS[f].leak, FIELD_DEFS[f].scale)}
        used |= {"authority_scale"} if AUTHORITY in self.fields else set()
        for attribute in OPTIONAL_ATTRIBUTES - used:
            del raw[attribute]
        if not self.per_airframe_rotor_speed:  # as older readers know the spec
            del raw["per_airframe_rotor_speed"]
        return json.dumps(raw, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ObservationSpec:
        raw = json.loads(text)
        raw["fields"] = tuple(raw["fields"])
        return cls(**raw)


def start_motor_output(spec: ObservationSpec, rotor_speed: np.ndarray) -> np.ndarray:
    """The previous output where there is none (a start): the rotors' steady-state command."""
    return np.clip(np.asarray(rotor_speed, dtype=np.float64) * spec.rotor_speed_scale, 0.0, 1.0)


def observe_step(spec: ObservationSpec, setpoint: np.ndarray, gyro: np.ndarray,
                 rotor_speed: np.ndarray, out: np.ndarray | None = None,
                 motor_output: np.ndarray | None = None,
                 loop_delay: float | np.ndarray | None = None) -> np.ndarray:
    """One step's features, (..., step_size) float32, into `out` if given (any shape that
    holds them, e.g. a batch of one): each field's source times its scale, in the inputs'
    precision. An integrated field holds the integrator's input, the scaled error;
    `ObservationHistory` integrates it. `motor_output` is the previous tick's u (0..1),
    read only by a spec with that field; None at a start (`start_motor_output`). `loop_delay`:
    the loop's configured delay in ticks (a float, or one per batch row), which a spec with that
    field needs.

    One float64 vehicle runs on plain floats, column by column from the flattened table
    (numpy's per-call overhead on 3-vectors would cost more than the model each tick);
    anything else runs on arrays, field by field. The products are the same either way.
    """
    if spec.reads_motor_output and motor_output is None:
        motor_output = start_motor_output(spec, rotor_speed)
    if spec.reads_loop_delay and loop_delay is None:
        raise ValueError("this observation reads the loop's delay: give loop_delay (ticks)")
    # `is`: numpy's float64 descriptor is one object; an equal one that is not takes the array path.
    if setpoint.dtype is gyro.dtype is rotor_speed.dtype is _FLOAT64 and setpoint.ndim == gyro.ndim == 1:
        s, g = setpoint.tolist(), gyro.tolist()
        sources = [s[0] - g[0], s[1] - g[1], s[2] - g[2], *rotor_speed.tolist(), *g]
        if motor_output is not None:
            sources += np.asarray(motor_output, dtype=np.float64).tolist()
        if spec.reads_loop_delay:
            sources += [0.0] * (SOURCE_COLUMNS["loop_delay"][0] - len(sources)) + [float(loop_delay)]
        values = list(map(mul, spec._pick_sources(sources), spec.column_scales))  # loops in C
        if out is None:
            return np.array(values, dtype=np.float32)
        out[...] = values  # rounds each float64 to float32, as astype does
        return out
    sources = {"rate_error": np.subtract(setpoint, gyro), "rotor_speed": rotor_speed, "gyro": gyro,
               "motor_output": motor_output}
    if spec.reads_loop_delay:
        delay = np.asarray(loop_delay, dtype=np.float64)[..., None]
        sources["loop_delay"] = np.broadcast_to(delay, (*np.shape(setpoint)[:-1], 1))
    values = np.concatenate([sources[d.source] * scale for _, d, scale in spec.layout], axis=-1)
    if out is None:
        return values.astype(np.float32)
    out[...] = values
    return out


class ObservationHistory:
    """The last `memory` steps, newest first, for one vehicle or a batch of them.

    With integrated fields in the spec it also keeps their integrator states, one per batch
    row, and writes each (the root, for an RMS field) into each step it stores. `view` is
    the observation batch itself (…, size), updated in place: flight binds it as the model's
    input; `reset` and `push` return copies of it.
    """

    def __init__(self, spec: ObservationSpec, batch_shape: tuple[int, ...] = ()) -> None:
        self.spec = spec
        self._buf = np.zeros((*batch_shape, spec.memory, spec.step_size), dtype=np.float32)
        self.view = self._buf.reshape(*batch_shape, spec.size)
        self._newest = self._buf[..., 0, :]
        # Where a caller may build the next step for `record`/`start` in place: with memory 1
        # the newest slot itself, so nothing is copied (a step not recorded is overwritten next).
        self.staging = self._newest if spec.memory == 1 else np.zeros_like(self._newest)
        self._integrators = [(cols, np.float32(lam), rms,
                              np.zeros((*batch_shape, cols.stop - cols.start), dtype=np.float32))
                             for cols, lam, rms in spec.integrators]
        self._slope = None if spec.slope is None else AuthorityEstimate(spec, batch_shape)

    def start(self, step: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Fill the whole history with one step (the episode start); `mask` picks batch rows."""
        if mask is not None:
            kept_steps = self._buf.copy()
            kept_states = [state.copy() for *_, state in self._integrators]
            kept_slope = None if self._slope is None else self._slope.state.copy()
            self.start(step)
            self._buf[~mask] = kept_steps[~mask]
            for (*_, state), kept in zip(self._integrators, kept_states, strict=True):
                state[~mask] = kept[~mask]
            if self._slope is not None:
                self._slope.state[~mask] = kept_slope[~mask]
            return
        if step is not self._newest:
            self._newest[...] = step
        self._integrate(restart=True)
        self._buf[..., 1:, :] = self._newest[..., None, :]

    def record(self, step: np.ndarray) -> None:
        """Add one step as the newest, dropping the oldest."""
        if self.spec.memory > 1:
            self._buf[..., 1:, :] = self._buf[..., :-1, :]
        if step is not self._newest:
            self._newest[...] = step
        self._integrate(restart=False)

    def reset(self, step: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        self.start(step, mask)
        return self.observation()

    def push(self, step: np.ndarray) -> np.ndarray:
        self.record(step)
        return self.observation()

    def observation(self) -> np.ndarray:
        return self.view.copy()

    def _integrate(self, restart: bool) -> None:
        """Advance each integrator with the newest step's input and store its output there."""
        for cols, lam, rms, state in self._integrators:
            x = self._newest[..., cols]
            carried = np.float32(0.0) if restart else lam * state
            state[...] = carried + (np.float32(1.0) - lam) * (x * x if rms else x)
            self._newest[..., cols] = np.sqrt(state) if rms else state
        if self._slope is not None:
            self._slope.update(self._newest, restart)


class AuthorityEstimate:
    """The `authority` field's state, one per batch row: the last scaled gyro and the leaky means of
    x, y, x·y and x² per axis (module docstring), all float32 as on a flight controller."""

    def __init__(self, spec: ObservationSpec, batch_shape: tuple[int, ...]) -> None:
        from fcemu.firmware.mixer import BETAFLIGHT_QUAD_X

        self.cols, self.rotor = spec.slope  # type: ignore[misc]
        self.lam = np.float32(spec.authority_leak)
        self.scale = np.float32(spec.authority_scale)
        self.mix = np.asarray(BETAFLIGHT_QUAD_X, dtype=np.float32)  # (4 motors, 3 axes)
        self.state = np.zeros((*batch_shape, 5, 3), dtype=np.float32)  # gyro, x̄, ȳ, x·y‾, x²‾

    def update(self, newest: np.ndarray, restart: bool) -> None:
        """Read the newest step's scaled gyro (in the field's columns) and rotor shares; write the slope."""
        gyro = newest[..., self.cols].copy()
        thrust = newest[..., self.rotor] ** 2  # the shares' squares, motor by motor in a fixed order:
        x = thrust[..., 0:1] * self.mix[0]  # a matrix product would sum differently per batch shape
        for i in range(1, 4):
            x = x + thrust[..., i:i + 1] * self.mix[i]
        st = self.state
        if restart:
            st[..., 0, :], st[..., 1, :], st[..., 2:, :] = gyro, x, np.float32(0.0)
            st[..., 4, :] = x * x
        else:
            y = gyro - st[..., 0, :]
            st[..., 0, :] = gyro
            keep, new = self.lam, np.float32(1.0) - self.lam
            for k, value in ((1, x), (2, y), (3, x * y), (4, x * x)):
                st[..., k, :] = keep * st[..., k, :] + new * value
        mean_x, mean_y = st[..., 1, :], st[..., 2, :]
        cov = st[..., 3, :] - mean_x * mean_y
        var = st[..., 4, :] - mean_x * mean_x
        newest[..., self.cols] = self.scale * cov / (var + np.float32(AUTHORITY_EPSILON))
