"""Airframe data files and the MJCF model built from them.

Numbers live in `airframes/<name>.json` (FRD body axes, Betaflight motor order);
this module only turns them into a MuJoCo model. MuJoCo works in FLU body axes
over a z-up world (x north, y west); `FLU_FROM_FRD` converts both, once, at the
twin boundary.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.sim_bridge.airframe_file import (
    GRAVITY,
    OPTIONAL,
    REQUIRED,
    AirframeError,
    check_airframe_file,
    check_keys,
    number,
    read_json,
    suggestion,
    vector,
)

AIRFRAME_DIR = Path(__file__).parent / "airframes"
DEFAULT_AIRFRAME = "iris"  # what every command flies unless told otherwise
FLU_FROM_FRD = np.array([1.0, -1.0, -1.0])  # also NED <-> (north, west, up)
RIGS = ("rig", "free")
LEG_RADIUS = 0.01
ROTOR_BODY_INERTIA = (1e-6, 1e-6, 2e-6)  # kg·m², each rotor body's, unless the file gives its own


@dataclass(frozen=True)
class MotorSpec:
    """A motor's constants as the airframe file gives them; `sim_bridge.plant.MotorModel` is its dynamics."""

    max_rotor_speed: float  # rad/s at PWM max
    kf: float  # thrust = kf * omega^2, N/(rad/s)^2
    km: float  # yaw moment = km * thrust, m
    tau_up: float  # s
    tau_down: float  # s
    pwm_min: float = 1000.0
    pwm_max: float = 2000.0
    poles: int | None = None  # magnet poles of a brushless motor (eRPM = poles / 2 × RPM); None: brushed

    def pwm_for_rotor_speed(self, omega: float | np.ndarray) -> float | np.ndarray:
        span = self.pwm_max - self.pwm_min
        return self.pwm_min + span * np.asarray(omega) / self.max_rotor_speed


@dataclass(frozen=True)
class Airframe:
    name: str
    base_mass: float
    base_inertia: tuple[float, float, float]
    base_box: tuple[float, float, float]
    rotor_mass: float
    rotor_radius: float
    rotor_positions: np.ndarray  # (4, 3) FRD, m
    spin: np.ndarray  # (4,) +1 counter-clockwise, -1 clockwise, seen from above
    motor: MotorSpec
    gear_half_height: float
    rotor_body_inertia: tuple[float, float, float] = ROTOR_BODY_INERTIA  # kg·m², each rotor body (FRD axes)
    # What a real airframe adds (`sim_bridge.plant`); all off by default, as in the paper's twin.
    rate_damping: tuple[float, float, float] = (0.0, 0.0, 0.0)  # N·m·s/rad, FRD torque −D·Ω
    rotor_inertia: float = 0.0  # kg·m² about the spin axis: spin-up reaction and gyroscopic moment
    # FRD, m: the centre of mass off the rotors' centre; the thrust then turns the body (a quad's trim)
    centre_of_mass_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    esc_delay_ticks: int = 0  # PWM command → motor, whole physics steps
    gyro_delay_ticks: int = 0  # rate → gyro reading, whole physics steps
    # ESC telemetry as a real bus delivers it: late by whole steps, and each motor's frame lost
    # (its last sample held, with its old time) with this probability per step
    esc_telemetry_delay_ticks: int = 0
    esc_telemetry_loss: float = 0.0
    gyro_noise_std: float = 0.0  # rad/s, white, per sample
    gyro_vibration: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s per (rad/s)² of each rotor
    battery_voltage_full: float = 12.6  # V
    battery_sag_per_charge: float = 0.0  # V per A·s drawn
    battery_resistance: float = 0.0  # Ω, internal
    battery_current_per_thrust: float = 0.0  # A per N^1.5 of each rotor (momentum theory)
    battery_drawn_at_start: float = 0.0  # A·s already drawn when a flight starts (state of charge)
    effect_sources: tuple[tuple[str, str], ...] = ()  # (field, citation) as the file gives them
    # whose PID tune it flies: its own, or a variant's base's when the variant changes only effects
    tune_of: str = ""

    @property
    def battery_sags(self) -> bool:
        sags = self.battery_sag_per_charge or self.battery_resistance
        return bool(self.battery_current_per_thrust and sags)

    @property
    def body_torques(self) -> bool:
        """Any torque beside the rotors' thrust and drag: damping, spin-up reaction, gyroscopic."""
        return bool(any(self.rate_damping) or self.rotor_inertia or any(self.centre_of_mass_offset))

    @property
    def gyro_effects(self) -> bool:
        return bool(self.gyro_noise_std or any(self.gyro_vibration) or self.gyro_delay_ticks)

    @property
    def loop_delay_ticks(self) -> int:
        """Ticks from a motor command to the gyro reading that shows it, beyond the sample's own:
        the ESC protocol's and the gyro filters' delays, which a flight controller is configured with."""
        return self.esc_delay_ticks + self.gyro_delay_ticks

    @property
    def telemetry_effects(self) -> bool:
        return bool(self.esc_telemetry_delay_ticks or self.esc_telemetry_loss)

    @property
    def mass(self) -> float:
        return self.base_mass + 4 * self.rotor_mass

    @property
    def yaw_sign(self) -> np.ndarray:
        """FRD yaw moment per unit thrust sign: a CW prop twists the body CCW (negative yaw)."""
        return self.spin.astype(float)

    def thrust_to_weight(self, gravity: float = GRAVITY) -> float:
        """The four rotors' thrust at top speed over the weight."""
        return 4 * self.motor.kf * self.motor.max_rotor_speed**2 / (self.mass * gravity)

    def inertia(self) -> np.ndarray:
        """(3,) kg·m²: the whole airframe's moments about its centre of mass (body axes), rotors included."""
        rotors = self.rotor_positions
        com = rotors.sum(axis=0) * self.rotor_mass / self.mass
        base_offset = -com  # the base body's own centre sits at the body origin
        total = np.array(self.base_inertia, dtype=float) + 4 * np.array(self.rotor_body_inertia, dtype=float)
        for offset, mass in [(base_offset, self.base_mass), *((r - com, self.rotor_mass) for r in rotors)]:
            total += mass * (offset @ offset - offset**2)  # parallel axis, diagonal terms
        return total

    def max_angular_acceleration(self, gravity: float = GRAVITY) -> np.ndarray:
        """(3,) rad/s² on roll, pitch, yaw from the full differential thrust around hover.

        Each rotor's thrust moves by the same δ either way from hover, the weight still held:
        δ = min(T_max − T_hover, T_hover). Roll takes δ·Σ|y|, pitch δ·Σ|x|, yaw δ·k_M per rotor.
        """
        m = self.motor
        hover = self.mass * gravity / 4
        delta = min(m.kf * m.max_rotor_speed**2 - hover, hover)
        arms = np.abs(self.rotor_positions[:, :2]).sum(axis=0)
        torque = delta * np.array([arms[1], arms[0], 4 * m.km])
        return torque / self.inertia()

    def hover_rotor_speed(self, gravity: float = 9.81) -> float:
        return float(np.sqrt(self.mass * gravity / (4 * self.motor.kf)))

    def hover_pwm(self, gravity: float = 9.81) -> float:
        return float(self.motor.pwm_for_rotor_speed(self.hover_rotor_speed(gravity)))

    def hover_throttle(self, gravity: float = 9.81) -> float:
        """The collective setpoint (0..1, the firmware's throttle-to-PWM scale) that holds the weight."""
        return (self.hover_pwm(gravity) - PWM_MIN) / PWM_SPAN

    def scaled(self, mass: float = 1.0, inertia: float | tuple[float, float, float] = 1.0, kf: float = 1.0,
               km: float = 1.0, tau_up: float = 1.0, tau_down: float = 1.0, **effects: object) -> Airframe:
        """A copy with mass, inertia (one factor, or one per axis) and motor constants multiplied.

        `effects` sets effect fields (`effect_fields()`) to the values given, e.g. a
        randomisation's draw; in a per-axis value, None keeps this airframe's axis.
        """
        m = self.motor
        motor = replace(m, kf=m.kf * kf, km=m.km * km, tau_up=m.tau_up * tau_up,
                        tau_down=m.tau_down * tau_down)
        per_axis = inertia if isinstance(inertia, tuple | list) else (inertia,) * 3
        inertia_scaled = tuple(float(i) * f for i, f in zip(self.base_inertia, per_axis, strict=True))
        unknown = sorted(set(effects) - set(effect_fields()))
        if unknown:
            raise TypeError(f"scaled() got unknown effect(s) {unknown}; known: {effect_fields()}")
        for name, value in effects.items():
            if isinstance(value, tuple | list):
                effects[name] = tuple(float(getattr(self, name)[i]) if v is None else float(v)
                                      for i, v in enumerate(value))
        return replace(self, base_mass=self.base_mass * mass, base_inertia=inertia_scaled,
                       rotor_mass=self.rotor_mass * mass, motor=motor, **effects)  # type: ignore[arg-type]


# The file's "effects" keys (value in the unit the key names, plus its source) → Airframe fields.
EFFECT_KEYS = {
    "rate_damping_N_m_s_rad": "rate_damping",
    "rotor_inertia_kg_m2": "rotor_inertia",
    "centre_of_mass_offset_m": "centre_of_mass_offset",
    "esc_delay_ticks": "esc_delay_ticks",
    "gyro_delay_ticks": "gyro_delay_ticks",
    "esc_telemetry_delay_ticks": "esc_telemetry_delay_ticks",
    "esc_telemetry_loss_fraction": "esc_telemetry_loss",
    "gyro_noise_std_rad_s": "gyro_noise_std",
    "gyro_vibration_rad_s_per_rad_s2": "gyro_vibration",
    "battery_voltage_full_V": "battery_voltage_full",
    "battery_sag_V_per_A_s": "battery_sag_per_charge",
    "battery_resistance_ohm": "battery_resistance",
    "battery_current_A_per_N1_5": "battery_current_per_thrust",
    "battery_drawn_at_start_A_s": "battery_drawn_at_start",
}


def airframe_names() -> list[str]:
    return sorted(p.stem for p in AIRFRAME_DIR.glob("*.json") if "." not in p.stem)


# A variant with no other keys than these has its base's nominal physics, so flies its base's PID tune.
VARIANT_ONLY_KEYS = frozenset({"name", "source", "sources", "frame", "base", "effects"})


def _read(name_or_path: str | Path, variants: tuple[Path, ...] = ()) -> tuple[Path, dict]:
    path = Path(name_or_path)
    if not path.suffix:
        path = AIRFRAME_DIR / f"{name_or_path}.json"
    if not path.exists():
        raise FileNotFoundError(f"no airframe file {path} (shipped airframes: {', '.join(airframe_names())})")
    if path in variants:
        raise AirframeError(variants[-1], "base", f"{path} is its own base")
    raw = read_json(path)
    if "base" in raw:  # a variant: the base airframe's file with these keys (effects merged) replaced
        check_keys(path, "", raw, (), REQUIRED + OPTIONAL)
        if not isinstance(raw["base"], str) or not raw["base"]:
            raise AirframeError(path, "base", "must name the airframe this one varies")
        beside = path.parent / f"{raw['base']}.json"
        _, base = _read(beside if beside.exists() else raw["base"], (*variants, path))
        effects = {**base.get("effects", {}), **raw.get("effects", {})}
        tune_of = base.get("_tune_of", base["name"]) if not set(raw) - VARIANT_ONLY_KEYS else None
        raw = {**base, **raw, "effects": effects, "_tune_of": tune_of or raw.get("name") or path.stem}
    return path, raw


def _effects(path: Path, raw: dict) -> dict:
    values: dict = {}
    sources = []
    for key, entry in raw.get("effects", {}).items():
        where = f"effects.{key}"
        if key not in EFFECT_KEYS:
            raise AirframeError(path, where, f"unknown effect {key!r}{suggestion(key, tuple(EFFECT_KEYS))}")
        if not isinstance(entry, dict) or "value" not in entry:
            raise AirframeError(path, where, "expected an object {\"value\": ..., \"source\": ...}")
        name = EFFECT_KEYS[key]
        value = entry["value"]
        if isinstance(value, list):
            value = vector(path, f"{where}.value", value, strict=False,
                           low=None if name == "centre_of_mass_offset" else 0.0)
        elif name.endswith("_ticks"):
            whole = isinstance(value, int | float) and not isinstance(value, bool) and int(value) == value
            if not whole or value < 0:
                raise AirframeError(path, f"{where}.value",
                                    f"must be a whole number of ticks >= 0, got {value}")
            value = int(value)
        else:
            value = number(path, f"{where}.value", value, strict=name == "battery_voltage_full")
            if name == "esc_telemetry_loss" and value >= 1.0:
                raise AirframeError(path, f"{where}.value", f"a share of frames lost, below 1, got {value}")
        values[name] = value
        sources.append((name, str(entry.get("source", ""))))
    values["effect_sources"] = tuple(sources)
    return values


def effect_fields() -> tuple[str, ...]:
    """The Airframe fields of the effects, the names a randomisation draws."""
    return tuple(f.name for f in fields(Airframe) if f.name in EFFECT_KEYS.values())


def load_airframe(name_or_path: str | Path = DEFAULT_AIRFRAME) -> Airframe:
    """The airframe of a shipped name or a file; an `AirframeError` names the field of any problem."""
    path, raw = _read(name_or_path)
    return airframe_of(path, raw)


def airframe_of(path: Path, raw: dict) -> Airframe:
    """The airframe an airframe file's JSON `raw` describes (`path` names it in an error)."""
    raw = dict(raw)
    tune_of = raw.pop("_tune_of", None)
    check_airframe_file(path, raw)
    motors = raw["motors"]
    m = raw["motor"]
    return Airframe(
        name=raw["name"],
        base_mass=float(raw["base_mass_kg"]),
        base_inertia=tuple(float(v) for v in raw["base_inertia_kg_m2"]),  # type: ignore[arg-type]
        base_box=tuple(float(v) for v in raw["base_box_m"]),  # type: ignore[arg-type]
        rotor_mass=float(raw["rotor_mass_kg"]),
        rotor_radius=float(raw["rotor_radius_m"]),
        rotor_positions=np.array([mo["position_m"] for mo in motors], dtype=float),
        spin=np.array([1 if mo["spin"] == "ccw" else -1 for mo in motors]),
        motor=MotorSpec(
            max_rotor_speed=float(m["max_rotor_speed_rad_s"]),
            kf=float(m["thrust_coefficient_N_per_rad_s2"]),
            km=float(m["moment_constant_m"]),
            tau_up=float(m["time_constant_up_s"]),
            tau_down=float(m["time_constant_down_s"]),
            pwm_min=float(m.get("pwm_min_us", 1000)),
            pwm_max=float(m.get("pwm_max_us", 2000)),
            poles=m.get("poles"),
        ),
        gear_half_height=float(raw["landing_gear_half_height_m"]),
        rotor_body_inertia=tuple(float(v) for v in raw.get("rotor_body_inertia_kg_m2",  # type: ignore[arg-type]
                                                           ROTOR_BODY_INERTIA)),
        **_effects(path, raw),
        tune_of=tune_of or raw["name"],
    )


def _vec(v: np.ndarray | tuple[float, ...]) -> str:
    return " ".join(f"{float(x):.9g}" for x in v)


def build_mjcf(airframe: Airframe, rig: str, dt: float = 0.001) -> str:
    """MJCF for one rig: `rig` pins the centre of mass on a ball joint, `free` flies over a floor."""
    if rig not in RIGS:
        raise ValueError(f"unknown rig {rig!r}; choose one of {RIGS}")
    rotors_flu = airframe.rotor_positions * FLU_FROM_FRD
    com = rotors_flu.sum(axis=0) * airframe.rotor_mass / airframe.mass
    bx, by, bz = (s / 2 for s in airframe.base_box)
    rotors = "\n".join(
        f'      <body name="rotor{i + 1}" pos="{_vec(p)}">'
        f'<inertial pos="0 0 0" mass="{airframe.rotor_mass}"'
        f' diaginertia="{_vec(airframe.rotor_body_inertia)}"/>'
        f'<geom type="cylinder" size="{airframe.rotor_radius} 0.003" contype="0" conaffinity="0"'
        f' rgba="{".2 .2 .2" if airframe.spin[i] < 0 else ".7 .2 .2"} .5"/>'
        f'<site name="rotor{i + 1}" pos="0 0 0"/></body>'
        for i, p in enumerate(rotors_flu)
    )
    actuators = "\n".join(
        f'    <general name="motor{i + 1}" site="rotor{i + 1}" ctrllimited="false"'
        f' gear="0 0 1 0 0 {-airframe.spin[i] * airframe.motor.km:.9g}"/>'
        for i in range(4)
    )
    if rig == "rig":
        joint = f'<joint name="ball" type="ball" pos="{_vec(com)}" damping="0"/>'
        start = "0 0 1"
        floor = ""
        legs = ""
    else:
        joint = '<freejoint name="free"/>'
        start = f"0 0 {airframe.gear_half_height + LEG_RADIUS:.6g}"  # resting on the legs
        floor = '<geom name="floor" type="plane" size="20 20 0.1" rgba=".8 .8 .8 1"/>'
        h = airframe.gear_half_height
        legs = "\n".join(
            f'      <geom type="sphere" size="{LEG_RADIUS}" pos="{sx * bx * 0.6:.4f} {sy * by * 0.6:.4f}'
            f' {-h:.4f}" friction="1 0.01 0.001"/>'
            for sx in (-1, 1) for sy in (-1, 1)
        )
    return f"""<mujoco model="{airframe.name}-{rig}">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="{dt}" gravity="0 0 -9.81"/>
  <worldbody>
    {floor}
    <body name="base" pos="{start}">
      {joint}
      <inertial pos="0 0 0" mass="{airframe.base_mass}" diaginertia="{_vec(airframe.base_inertia)}"/>
      <geom type="box" size="{bx} {by * 0.3:.4f} {bz}" contype="1" conaffinity="1"
            rgba=".3 .3 .8 1"/>
{legs}
      <site name="imu" pos="{_vec(com)}"/>
{rotors}
    </body>
  </worldbody>
  <actuator>
{actuators}
  </actuator>
  <sensor>
    <gyro name="gyro" site="imu"/>
    <accelerometer name="accel" site="imu"/>
  </sensor>
</mujoco>
"""
