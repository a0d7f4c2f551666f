"""From the fits of `evaluation.identify` to an airframe file `--airframe` flies.

What a rate log gives are ratios: the torque each rotor speed makes per unit of inertia, the
motors' lag and delay, the speed a command asks for, the command that hovers. A file needs
absolute numbers, so the base airframe gives what the log cannot (mass, geometry, the rotor
and body sizes, the battery), and the rest follows: k_F from the mass and the hover rotor speed,
roll's and pitch's inertia from k_F over their fitted effectiveness, the yaw inertia from the
rates' gyroscopic coupling, (I_yy − I_zz)/I_xx and (I_zz − I_xx)/I_yy, and the yaw moment
constant from it and the yaw effectiveness. A log whose rates never coupled keeps the base's
moment constant and derives I_zz from it. Each number's `sources` entry says which it is:
"identified from LOG" with its 95 % interval, derived, or the base's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fcemu.evaluation.identify import (
    AXES,
    TAU_UP_RANGE_S,
    Z95,
    Estimate,
    MotorFit,
    RateFit,
    fit_motors,
    fit_rates,
    fit_without_rpm,
    hover_command,
    levers,
)
from fcemu.evaluation.identify_gyro import GyroFit, fit_gyro
from fcemu.evaluation.identify_log import FlightLog, LogError
from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.sim_bridge.airframe import EFFECT_KEYS, Airframe
from fcemu.sim_bridge.airframe_file import GRAVITY

# MuJoCo computes the gyro before it integrates a step, so the twin's gyro reads the rate one
# tick late with no delay configured: that tick of the measured delay is the twin's own.
TWIN_GYRO_LAG_TICKS = 1
TWIN_DT = 0.001  # s: the physics step the file's *_ticks count (the twin at 1 kHz)
YAW_INERTIA_TOLERANCE = 0.2  # I_zz from the coupling only within ± this share of its value (95 %)
ATTRIBUTE_OF_EFFECT = {attribute: key for key, attribute in EFFECT_KEYS.items()}


@dataclass(frozen=True)
class Identification:
    log: FlightLog
    base: Airframe
    base_label: str  # how the base was named (a shipped name or a file)
    motors: MotorFit
    rates: RateFit
    hover: Estimate  # the collective, 0..1
    gyro: GyroFit
    spin_note: str = ""  # which way the props turn, and how it is known

    @property
    def hover_rotor_speed(self) -> Estimate:
        a, b, u = self.motors.speed_at_zero, self.motors.speed_per_command, self.hover
        value = a.value + b.value * u.value
        std = np.sqrt(sum(((e.high - e.low) / (2 * 1.959964)) ** 2 * w**2
                          for e, w in ((a, 1.0), (b, u.value), (u, b.value))))
        return Estimate.normal(value, float(std))


def identify(log: FlightLog, base: Airframe, base_label: str) -> Identification:
    """The fits on `base`'s geometry; its props turned the other way round where the log's header
    says so, or where, unsaid, the yaw answers the motors the other way (props "out")."""
    props_out = bool(base.spin[0] > 0)
    if log.props_reversed is not None:
        told = log.props_reversed != props_out
        spin_note = f"props {'out' if log.props_reversed else 'in'}: the log's header (yaw_motors_reversed)"
        base = _spun(base, log.props_reversed) if told else base
        motors, rates = _fits(log, base)
    else:
        motors, rates = _fits(log, base)
        c = [axis.effectiveness.value for axis in rates.axes]
        spin_note = f"props {'out' if props_out else 'in'}, as the base's: the yaw answers the motors so"
        if c[0] > 0 and c[1] > 0 and c[2] < 0:
            base = _spun(base, not props_out)
            motors, rates = _fits(log, base)
            spin_note = (f"props {'in' if props_out else 'out'}: the yaw answered the motors "
                         "the other way round "
                         f"from the base's spins (yaw effectiveness {c[2]:.3g}), and the header does not say")
    hover = hover_command(log)
    if not 0.02 < hover.value < 0.98:
        raise LogError(f"{log.path}: the collective holds at {hover.value:.2f}, not a hover")
    gyro = fit_gyro(log, base.motor.max_rotor_speed, rates.speed)
    return Identification(log, base, base_label, motors, rates, hover, gyro, spin_note)


def _fits(log: FlightLog, base: Airframe) -> tuple[MotorFit, RateFit]:
    lever = levers(base)
    if log.rotor_speed is not None:
        return fit_motors(log), fit_rates(log, log.rotor_speed, lever)
    return fit_without_rpm(log, base, lever)


def _spun(base: Airframe, props_out: bool) -> Airframe:
    """`base` with motor 1 counter-clockwise (props out) or clockwise (in), the others to match."""
    sign = 1 if props_out else -1
    return replace(base, spin=np.array([sign, -sign, -sign, sign]))


def _effects_document(airframe: Airframe) -> dict:
    sources = dict(airframe.effect_sources)
    out = {}
    for attribute, key in ATTRIBUTE_OF_EFFECT.items():
        value = getattr(airframe, attribute)
        out[key] = {"value": list(value) if isinstance(value, tuple) else value,
                    "source": sources.get(attribute, "")}
    return out


def airframe_document(airframe: Airframe, source: str, sources: dict[str, str]) -> dict:
    """The airframe file of `airframe` (`sim_bridge.airframe.load_airframe` reads it back)."""
    m = airframe.motor
    names = ("rear_right", "front_right", "rear_left", "front_left")
    doc = {
        "name": airframe.name, "source": source,
        "frame": "FRD body axes, metres; motors in Betaflight Quad X order",
        "base_mass_kg": airframe.base_mass, "base_inertia_kg_m2": list(airframe.base_inertia),
        "base_box_m": list(airframe.base_box), "rotor_mass_kg": airframe.rotor_mass,
        "rotor_radius_m": airframe.rotor_radius,
        "rotor_body_inertia_kg_m2": list(airframe.rotor_body_inertia),
        "motors": [{"name": name, "position_m": [float(v) for v in p], "spin": "ccw" if s > 0 else "cw"}
                   for name, p, s in zip(names, airframe.rotor_positions, airframe.spin, strict=True)],
        "motor": {"max_rotor_speed_rad_s": m.max_rotor_speed, "thrust_coefficient_N_per_rad_s2": m.kf,
                  "moment_constant_m": m.km, "time_constant_up_s": m.tau_up,
                  "time_constant_down_s": m.tau_down,
                  "pwm_min_us": m.pwm_min, "pwm_max_us": m.pwm_max, "poles": m.poles},
        "landing_gear_half_height_m": airframe.gear_half_height,
        "sources": sources,
        "effects": _effects_document(airframe),
    }
    return json.loads(json.dumps(doc, default=float))


def _scaled(e: Estimate, factor: float) -> Estimate:
    lo, hi = sorted((e.low * factor, e.high * factor))
    return Estimate(e.value * factor, lo, hi)


def _nonnegative(e: Estimate, log_name: str, unit: str) -> tuple[float, str]:
    if e.low <= 0.0:
        return 0.0, f"identified from {log_name}: {e.text(unit)}; not distinguishable from 0, so 0"
    return e.value, f"identified from {log_name}: {e.text(unit)}"


def identified_document(ident: Identification, name: str) -> dict:
    """The airframe file: the base's, with every number the log gives replaced and sourced."""
    base, log, mf, rf = ident.base, ident.log, ident.motors, ident.rates
    at = f"identified from {log.name}"
    kept = f"from the base airframe {ident.base_label} (a rate log cannot give it)"
    sources = {key: kept for key in ("base_mass_kg", "base_box_m", "rotor_mass_kg", "rotor_radius_m",
                                     "rotor_body_inertia_kg_m2", "motors", "landing_gear_half_height_m",
                                     "motor.moment_constant_m", "motor.poles")}
    omega_h = ident.hover_rotor_speed
    b = mf.speed_per_command.value
    if mf.from_rpm:
        max_speed = mf.speed_at_zero.value + b
        pwm_min = PWM_MIN - PWM_SPAN * mf.speed_at_zero.value / b
        line = (f"{at}: ESC rpm against the motor command, ω = a + b·u with a "
                f"{mf.speed_at_zero.text(' rad/s')}, b {mf.speed_per_command.text(' rad/s')}")
        sources["motor.max_rotor_speed_rad_s"] = f"{line}; a + b"
        sources["motor.pwm_min_us"] = f"{line}; where ω = 0 on the 1000-2000 µs scale"
        kf = base.mass * GRAVITY / (4 * omega_h.value**2)
        rel = 2 * (omega_h.high - omega_h.low) / (2 * omega_h.value)
        kf_est = Estimate(kf, kf * (1 - rel), kf * (1 + rel))
        sources["motor.thrust_coefficient_N_per_rad_s2"] = (
            f"derived: the base's mass {base.mass:.4g} kg held by four rotors at the hover speed "
            f"{omega_h.text(' rad/s')} ({at}: hover command {ident.hover.text()}); {kf_est.text()}")
        effectiveness_scale = 1.0
    else:
        m = base.motor
        pwm_min, kf = m.pwm_min, m.kf
        omega_h = Estimate.normal(base.hover_rotor_speed(), 0.0)
        hover_pwm = PWM_MIN + PWM_SPAN * ident.hover.value
        max_speed = omega_h.value * (m.pwm_max - m.pwm_min) / (hover_pwm - m.pwm_min)
        sources["motor.thrust_coefficient_N_per_rad_s2"] = f"{kept}; no ESC rpm in {log.name}"
        sources["motor.pwm_min_us"] = f"{kept}; no ESC rpm in {log.name}"
        sources["motor.max_rotor_speed_rad_s"] = (
            f"derived: the base's hover rotor speed at the hover command {ident.hover.text()} ({at}); "
            "no ESC rpm in the log")
        effectiveness_scale = (m.max_rotor_speed / max_speed) ** 2  # the fit's speeds were the base line's
    sources["motor.pwm_max_us"] = "the firmware's PWM scale (1000-2000 µs)"
    how = "ESC rpm against the command" if mf.from_rpm else "the rate response to the motor commands"
    tau_up, tau_down = mf.tau_up.value, mf.tau_down.value
    if mf.at_edge:
        for key, e in (("up", mf.tau_up), ("down", mf.tau_down)):
            sources[f"motor.time_constant_{key}_s"] = (
                f"{at} ({how}): {e.value:.4g} s, at an end of the range searched ({TAU_UP_RANGE_S[0]:g} to "
                f"{TAU_UP_RANGE_S[1]:g} s spin-up): the log says only that it is no further in")
    else:
        sources["motor.time_constant_up_s"] = f"{at} ({how}): {mf.tau_up.text(' s')}"
        sources["motor.time_constant_down_s"] = f"{at} ({how}): {mf.tau_down.text(' s')}"
    sources["motors"] = f"positions {kept}; {ident.spin_note}"
    c = [_scaled(rf.axes[i].effectiveness, effectiveness_scale) for i in range(3)]
    if min(ci.value for ci in c) <= 0:
        raise LogError(f"{log.path}: a motor command turns the vehicle the wrong way round "
                       f"({', '.join(f'{a} {ci.value:.3g}' for a, ci in zip(AXES, c, strict=True))}): "
                       "motor order or spins differ from the base's")
    roll_pitch = [kf / c[0].value, kf / c[1].value]
    izz = yaw_inertia(roll_pitch, rf.axes[0].coupling, rf.axes[1].coupling)
    if izz is not None and not is_rigid_body([*roll_pitch, izz.value]):
        izz = None  # the coupling's reading makes no body: the base's k_M instead, said below
    if izz is None and is_rigid_body([*roll_pitch, kf * base.motor.km / c[2].value]):
        km = base.motor.km
        izz_text = "k_F·k_M over the yaw effectiveness (k_M the base's: the log's rates never coupled)"
    elif izz is None:
        base_i = base.inertia()
        shape = base_i[2] / (base_i[0] + base_i[1])
        # inside the rigid bodies' interval for I_zz, |I_xx − I_yy| … I_xx + I_yy, with a margin
        low, high = abs(roll_pitch[0] - roll_pitch[1]), sum(roll_pitch)
        shape = float(np.clip(shape, low / high + 0.05, 0.95))
        km = shape * sum(roll_pitch) * c[2].value / kf
        sources["motor.moment_constant_m"] = (
            f"derived: the yaw effectiveness {c[2].text()} × I_zz / k_F, I_zz from the base's shape (below)")
        izz_text = (f"{shape:.3f} of roll's and pitch's sum, as the base {ident.base_label}'s "
                    "(the log's rates never "
                    "coupled, and the base's k_M makes no rigid body of this quad)")
    else:
        km = c[2].value * izz.value / kf
        sources["motor.moment_constant_m"] = (f"derived: the yaw effectiveness {c[2].text()} × I_zz / k_F, "
                                              f"I_zz from the gyroscopic coupling: {izz.text(' kg·m²')}")
        izz_text = (f"from roll's and pitch's gyroscopic coupling {at} (roll {rf.axes[0].coupling.text()}, "
                    f"pitch {rf.axes[1].coupling.text()})")
    total = [*roll_pitch, kf * km / c[2].value]
    rotors_part = base.inertia() - np.array(base.base_inertia)
    inertia = [t - r for t, r in zip(total, rotors_part, strict=True)]
    if min(inertia) <= 0:
        raise LogError(f"{log.path}: the identified inertia {total} is below the rotors' own share: the base "
                       f"{ident.base_label} does not fit this vehicle")
    if not is_rigid_body(total):
        raise LogError(f"{log.path}: the identified inertia "
                       f"({', '.join(f'{v:.3g}' for v in total)} kg·m²) is no "
                       "rigid body (an axis above the sum of the other two): the yaw effectiveness "
                       f"({c[2].text()}) and the base {ident.base_label}'s k_M disagree; try a --base nearer "
                       "this quad")
    parts = [f"{a} {ci.text(' rad/s² per (N·m/k_F)')}" for a, ci in zip(AXES, c, strict=True)]
    sources["base_inertia_kg_m2"] = (f"derived: roll and pitch k_F over the effectiveness {at} "
                                     f"({'; '.join(parts)}); yaw {izz_text}; less the rotors' share by the "
                                     "base's geometry")
    per_tick = log.dt / TWIN_DT  # the log's samples in the twin's physics steps
    delay_esc = round(mf.delay_ticks * per_tick)
    filter_ticks = round(log.gyro_filter_lag_s / TWIN_DT)
    delay_gyro = max(0, round(rf.gyro_delay_ticks * per_tick) - TWIN_GYRO_LAG_TICKS - filter_ticks)
    effects = {}
    damping, damping_text = [], []
    for i in range(3):
        value, text = _nonnegative(rf.axes[i].damping, log.name, " /s")
        damping.append(value * (total[i]))
        damping_text.append(f"{AXES[i]} {text}")
    effects["rate_damping"] = (tuple(damping), "; ".join(damping_text) + " (× the derived inertia)")
    weight = base.mass * GRAVITY  # the thrust that holds the hover, about the flight's mean
    offset = [0.0, 0.0, 0.0]
    offset_text = []
    for i, (axis, share) in enumerate(((1, total[0]), (0, -total[1]))):
        bias = rf.axes[i].bias
        if bias.low > 0 or bias.high < 0:
            offset[axis] = bias.value * share / weight
        offset_text.append(f"{AXES[i]} {bias.text(' rad/s²')}")
    effects["centre_of_mass_offset"] = (tuple(offset), (
        f"{at}: the steady roll and pitch acceleration the motors' mix leaves "
        f"({'; '.join(offset_text)}; 0 where "
        "not distinguishable from 0) × the derived inertia over the weight: "
        "the thrust off the centre of mass"))
    spin = rf.axes[2].spin_up
    if spin is not None:
        value, text = _nonnegative(spin, log.name, "")
        effects["rotor_inertia"] = (value * total[2], f"yaw spin-up reaction {text} (× the derived I_zz)")
    esc_text = (f"{at}: ESC rpm against the command, the delay that fits best" if mf.from_rpm else
                f"no ESC rpm in {log.name}: the whole command-to-gyro delay is given to the gyro")
    effects["esc_delay_ticks"] = (delay_esc, esc_text)
    gyro_text = (f"{at}: {rf.gyro_delay_ticks * log.dt * 1e3:.0f} ms from rotor speed to gyro, less the "
                 f"twin's own {TWIN_GYRO_LAG_TICKS} tick"
                 + (f" and the logged gyro's filters' {log.gyro_filter_lag_s * 1e3:.2f} ms "
                    f"({log.gyro_filter_note}: the controller's own filters add it)" if filter_ticks else ""))
    effects["gyro_delay_ticks"] = (delay_gyro, gyro_text)
    effects["gyro_noise_std"] = (ident.gyro.noise_std, f"{at}: {ident.gyro.noise_how}")
    vibration = [_nonnegative(e, log.name, "") for e in ident.gyro.vibration]
    how = ("the gyro against the rotors' angles from the ESC rpm" if ident.gyro.from_angles else
           "the gyro's power above the rates' band against the rotor speeds' fourth power")
    effects["gyro_vibration"] = (tuple(v for v, _ in vibration),
                                 f"{how}: " + "; ".join(f"{a} {text}" for a, (_, text) in zip(AXES, vibration,
                                                                                              strict=True)))
    airframe = ident.base.scaled(**{k: v for k, (v, _) in effects.items()})
    base_sources = dict(ident.base.effect_sources)
    effect_sources = tuple((attr, effects[attr][1] if attr in effects else
                            f"{kept}: {base_sources.get(attr, '')}".rstrip(": "))
                           for attr in ATTRIBUTE_OF_EFFECT)
    motor = replace(base.motor, max_rotor_speed=float(max_speed), kf=float(kf), km=float(km),
                    tau_up=float(tau_up), tau_down=float(tau_down), pwm_min=float(pwm_min),
                    pwm_max=PWM_MIN + PWM_SPAN)
    airframe = replace(airframe, name=name, base_inertia=tuple(float(v) for v in inertia), motor=motor,
                       effect_sources=effect_sources)
    source = (f"Identified by fcemu identify from {log.name} ({len(log.t)} samples at {1 / log.dt:.0f} Hz, "
              f"motor commands from {log.command_source}{', ESC rpm' if mf.from_rpm else ', no ESC rpm'}) "
              f"on the base airframe {ident.base_label}." + "".join(f" {note}." for note in log.notes))
    return airframe_document(airframe, source, sources)


def is_rigid_body(inertia: list[float]) -> bool:
    """Principal moments a rigid body can have: positive, each below the sum of the other two."""
    a, b, c = inertia
    return min(inertia) > 0 and a < b + c and b < a + c and c < a + b


def yaw_inertia(roll_pitch: list[float], roll: Estimate, pitch: Estimate) -> Estimate | None:
    """I_zz from the gyroscopic coupling's two readings, g_roll = (I_yy − I_zz)/I_xx and
    g_pitch = (I_zz − I_xx)/I_yy, weighted by their intervals; None where the log did not couple
    the rates well enough to say (its interval wider than `YAW_INERTIA_TOLERANCE` of the value)."""
    ixx, iyy = roll_pitch
    readings = [(iyy - roll.value * ixx, ixx * (roll.high - roll.low) / (2 * Z95)),
                (ixx + pitch.value * iyy, iyy * (pitch.high - pitch.low) / (2 * Z95))]
    weights = [1.0 / std**2 for _, std in readings if std > 0]
    if len(weights) < 2:
        return None
    value = sum(w * v for w, (v, _) in zip(weights, readings, strict=True)) / sum(weights)
    std = sum(weights) ** -0.5
    if value <= 0 or Z95 * std > YAW_INERTIA_TOLERANCE * value:
        return None
    return Estimate.normal(value, std)


def write_airframe(doc: dict, path: Path) -> Airframe:
    """Write the file only once it reads back as `--airframe` would read it (its checks refuse an
    unflyable one, and then nothing is written)."""
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.sim_bridge.airframe_file import AirframeError

    path.parent.mkdir(parents=True, exist_ok=True)
    draft = path.with_name(f".{path.name}.draft.json")
    draft.write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    try:
        load_airframe(draft)
    except AirframeError as exc:
        draft.unlink()
        raise LogError(f"the identified airframe is not one fcemu flies, so {path} is not written: "
                       f"{str(exc).replace(str(draft), path.name)}") from None
    draft.replace(path)
    return load_airframe(path)
