"""The Iris PID tune carried over to another airframe by the loop's physics: the start of
`fcemu tune` (`training.pid_tune`, whose module doc derives it) and the PID that flies an
airframe's identification flight where no tune is shipped for it (`evaluation.identify_flight`).

Per axis, B is the angular acceleration per unit PID output (demand → mixer → PWM → rotor speed
→ thrust at hover → torque → rate, linearised at hover from the MuJoCo rig), and τ the motor
lag plus any ESC and gyro delay:

    kp = kp_r·(B_r/B)·(τ_r/τ)      ki = ki_r·(B_r/B)·(τ_r/τ)²
    kd = kd_r·(B_r/B)              kff = kff_r·(B_r/B)      filter cut-offs ×τ_r/τ
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from fcemu.firmware.mixer import QuadXMixer
from fcemu.sim_bridge.airframe import Airframe, effect_fields

AXES = ("roll", "pitch", "yaw")
REFERENCE = ("iris", "iris")  # (airframe, preset) the start is carried over from
# The tune's filter knobs: (setting, search step, (lowest, highest) for the reference airframe);
# cut-offs carry over with τ, within what a 1 kHz loop can run.
FILTER_KNOBS = (("gyro_lowpass_hz", 1.4, (50.0, 450.0)), ("dterm_lowpass_hz", 1.4, (20.0, 250.0)),
                ("ff_lowpass_hz", 1.4, (10.0, 250.0)))


def per_axis(values: np.ndarray) -> dict[str, float]:
    return {a: round(float(v), 2) for a, v in zip(AXES, values, strict=True)}


@dataclass(frozen=True)
class LoopPhysics:
    """What sets an airframe's loop gain and crossover (module doc)."""

    authority: np.ndarray  # (3,) B: rad/s² per unit of PID output at hover, roll/pitch/yaw
    lag_s: float  # τ: the motor's mean time constant plus the ESC and gyro delays

    def to_json(self) -> dict[str, Any]:
        return {"authority_rad_s2": per_axis(self.authority), "lag_s": round(self.lag_s, 5)}


def nominal(airframe: Airframe) -> Airframe:
    """The airframe with every effect at its nominal-twin default (what `rig_constants` reads)."""
    defaults = {f.name: f.default for f in fields(Airframe) if f.name in effect_fields()}
    return replace(airframe, **defaults)


def loop_physics(airframe: Airframe, mixer: QuadXMixer | None = None, dt: float = 0.001) -> LoopPhysics:
    from fcemu.evaluation.bound import rig_constants

    mixer = mixer or QuadXMixer()
    rig = rig_constants(nominal(airframe), dt)
    m = airframe.motor
    hover = airframe.hover_rotor_speed()
    speed_per_demand = mixer.out_range * m.max_rotor_speed / (m.pwm_max - m.pwm_min)
    thrust_per_demand = 2.0 * m.kf * hover * speed_per_demand  # d(kf·ω²)/d(demand) at hover
    table = np.array(mixer.table)  # (4 motors, 3 axes)
    authority = np.array([rig.B[j] @ table[:, j] for j in range(3)]) * thrust_per_demand
    lag = 0.5 * (m.tau_up + m.tau_down) + dt * (airframe.esc_delay_ticks + airframe.gyro_delay_ticks)
    return LoopPhysics(authority, lag)


def gain_scale(ref: LoopPhysics, new: LoopPhysics) -> tuple[np.ndarray, float, dict[str, np.ndarray]]:
    """(B_r/B per axis, τ_r/τ, each gain's factor from the reference airframe to the new: module doc)."""
    gain = ref.authority / new.authority
    speed = ref.lag_s / new.lag_s
    return gain, speed, {"kp": gain * speed, "ki": gain * speed**2, "kd": gain, "kff": gain}


def carried_over(reference: dict[str, Any], ref: LoopPhysics, new: LoopPhysics) -> dict[str, Any]:
    """The reference preset's gains carried over to an airframe of other physics (module doc)."""
    gain, speed, scale = gain_scale(ref, new)
    preset = json.loads(json.dumps(reference))
    pid = preset["pid"]
    for key, factor in scale.items():
        pid[key] = [float(f"{v * f:.9g}") for v, f in zip(pid[key], factor, strict=True)]
    # An axis with less authority than the reference's gets at least the reference's angular
    # acceleration at the limit, as far as the whole output range allows.
    pid["pidsum_limit"] = [float(f"{min(1.0, v * max(1.0, g)):.9g}")
                           for v, g in zip(pid["pidsum_limit"], gain, strict=True)]
    for key, _, (_, highest) in FILTER_KNOBS:
        if pid.get(key, 0.0) > 0.0:
            pid[key] = float(f"{min(pid[key] * speed, highest):.9g}")
    return preset


def mixer_for(preset: dict[str, Any], airframe: Airframe) -> dict[str, Any]:
    """The preset's mixer settings for `airframe`: yaw reversed where its props spin out (motor 1
    counter-clockwise), as Betaflight's yaw_motors_reversed and fcemu's firmware fly it."""
    mixer = dict(preset.get("mixer", {}))
    if airframe.spin[0] > 0:
        mixer["yaw_reversed"] = True
    return mixer


def iris_tune_carried_over(airframe: Airframe) -> dict[str, Any]:
    """The reference tune carried over to `airframe` by the loop's physics, as a preset."""
    from fcemu.firmware.pid_controller import load_preset
    from fcemu.sim_bridge.airframe import load_airframe

    reference = load_preset(REFERENCE[1])
    ref_physics = loop_physics(load_airframe(REFERENCE[0]), QuadXMixer(**reference["mixer"]))
    new_physics = loop_physics(airframe, QuadXMixer(**mixer_for(reference, airframe)))
    start = carried_over(reference, ref_physics, new_physics)
    start["name"] = f"pid_{airframe.name}"
    start["mixer"] = mixer_for(reference, airframe)
    return start
