"""Airframes drawn from a wide distribution of quads: files a twin, `fcemu tune` and `fcemu fit` read.

One rate policy for every quad is trained and judged across quads from a 20 g whoop to a 3 kg
camera ship, and checked on a draw of them it was not trained on. `AirframeRanges` is that
distribution, declared once; `draw_airframe` turns a generator's draws into an airframe file
(the JSON `sim_bridge.airframe.load_airframe` reads), each number's basis in its `sources`.

Mass, thrust-to-weight and motor lag are drawn log-uniform over their ranges, each on its own:
the shipped twins show no law between size and lag (the 27 g crazyflie's 72 ms, the Iris's
12.5 ms). The arm is not: a 20 g quad has 40 mm arms and a 3 kg one 300 mm ones, so it follows
the mass by a law through the shipped airframes (crazyflie, racer5, iris, x500, the held-out
hummingbird and 7-inch), scattered about it and clipped to its range. The propeller, its tip
speed, its drag-to-thrust ratio and the inertia's share of mass × arm² are drawn over the spans
those airframes show; the aerodynamic damping and the rotor's inertia follow from the drawn
numbers as the Iris's own do (its file's sources). Sensor effects are drawn from the ranges the default
policy is trained under (iris_sensors.randomization.json), which are a flight controller's, not
an airframe's; battery and vibration effects are left out (they scale with a pack and a frame
this draw does not model).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.firmware.errors import UserError
from fcemu.sim_bridge.airframe import Airframe, airframe_of, load_airframe
from fcemu.sim_bridge.airframe_file import GRAVITY, QUAD_X_SIGNS
from fcemu.sim_bridge.relative_ranges import inflow_damping, motor_torque_bound, rotor_drag_damping_yaw

# The propeller's pitch circle stays clear of its neighbour's: adjacent rotors are √2 arms apart.
PROP_SHARE_OF_ARM = (0.4, 0.62)


@dataclass(frozen=True)
class AirframeRanges:
    """The distribution: each pair a (low, high) range; what a draw may never leave."""

    mass_kg: tuple[float, float] = (0.02, 3.0)
    thrust_to_weight: tuple[float, float] = (1.5, 12.0)
    motor_tau_s: tuple[float, float] = (0.010, 0.120)  # spin-up; spin-down 1-1.6 × that, within the range
    arm_m: tuple[float, float] = (0.03, 0.35)
    arm_scatter: float = 1.45  # about `arm_for_mass`, a log-uniform factor this far either way
    # The spans of the shipped airframes: tip 53-211 m/s, k_M / r 0.04-1.09, I_xx / (m · arm²) 0.09-0.34.
    tip_speed_m_s: tuple[float, float] = (50.0, 215.0)  # the propeller's tip at full speed
    drag_to_thrust_per_radius: tuple[float, float] = (0.04, 1.1)  # k_M / r, log-uniform
    inertia_share: tuple[float, float] = (0.08, 0.4)  # I_xx / (m · arm²)
    # The sensor effects, as iris_sensors.randomization.json draws them; the ESC delay also at
    # Betaflight's 1 tick (iris_realistic.json) where that file holds it at 2.
    esc_delay_ticks: tuple[int, int] = (1, 2)
    gyro_delay_ticks: tuple[int, int] = (0, 3)
    gyro_noise_std_rad_s: tuple[float, float] = (0.0, 0.0214)
    esc_telemetry_delay_ticks: tuple[int, int] = (0, 5)
    esc_telemetry_loss: tuple[float, float] = (0.0, 0.05)


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _scattered(rng: np.random.Generator, value: float, spread: float, box: tuple[float, float]) -> float:
    return float(np.clip(value * _log_uniform(rng, 1.0 / spread, spread), *box))


def arm_for_mass(mass_kg: float) -> float:
    """The centre-to-motor arm a quad of `mass_kg` has, a power law through the shipped quads (the
    crazyflie 0.027 kg, 40 mm; racer5 0.83 kg, 109 mm; the 7-inch 0.95 kg, 163 mm; the Iris 1.6 kg,
    239 mm): each within `arm_scatter` of it."""
    return 0.16 * mass_kg**0.36


def draw_airframe(rng: np.random.Generator, name: str,
                  ranges: AirframeRanges = AirframeRanges()) -> dict[str, Any]:
    """One airframe file's JSON, drawn from `ranges` with `rng`."""
    mass = _log_uniform(rng, *ranges.mass_kg)
    arm = _scattered(rng, arm_for_mass(mass), ranges.arm_scatter, ranges.arm_m)
    radius = arm * rng.uniform(*PROP_SHARE_OF_ARM)
    thrust_to_weight = _log_uniform(rng, *ranges.thrust_to_weight)
    tip = _log_uniform(rng, *ranges.tip_speed_m_s)
    omega_max = tip / radius
    kf = thrust_to_weight * mass * GRAVITY / (4.0 * omega_max**2)
    km = radius * _log_uniform(rng, *ranges.drag_to_thrust_per_radius)
    tau_up = _log_uniform(rng, *ranges.motor_tau_s)
    tau_down = float(np.clip(tau_up * rng.uniform(1.0, 1.6), *ranges.motor_tau_s))
    ixx = mass * arm**2 * rng.uniform(*ranges.inertia_share)
    iyy = ixx * rng.uniform(0.9, 1.2)
    izz = (ixx + iyy) * rng.uniform(0.8, 1.0)
    half = arm / math.sqrt(2.0)
    spins = ("cw", "ccw", "ccw", "cw")
    raw = {
        "name": name,
        "source": (f"Drawn by `sim_bridge.airframe_draw` (mass {mass:.3g} kg, thrust-to-weight "
                   f"{thrust_to_weight:.3g}, arm {arm * 1000:.0f} mm, motor lag {tau_up * 1000:.0f} ms): "
                   "no real quad's measurements."),
        "frame": "FRD body axes, metres; motors in Betaflight Quad X order",
        "base_mass_kg": mass,
        "base_inertia_kg_m2": [ixx, iyy, izz],
        "base_box_m": [1.2 * half, 1.2 * half, 0.25 * arm],
        "rotor_mass_kg": 0.0,
        "rotor_body_inertia_kg_m2": [0.0, 0.0, 0.0],
        "rotor_radius_m": radius,
        "motors": [{"name": place.replace(" ", "_"), "position_m": [sx * half, sy * half, 0.0], "spin": spin}
                   for (sx, sy, place), spin in zip(QUAD_X_SIGNS, spins, strict=True)],
        "motor": {"max_rotor_speed_rad_s": omega_max, "thrust_coefficient_N_per_rad_s2": kf,
                  "moment_constant_m": km, "time_constant_up_s": tau_up, "time_constant_down_s": tau_down,
                  "pwm_min_us": 1000, "pwm_max_us": 2000, "poles": 14},
        "landing_gear_half_height_m": 0.125 * arm,
        "sources": _SOURCES,
    }
    # The airframe's own effects by the estimates the relative ranges scale to any airframe (the
    # Iris's file's sources), then the flight controller's, drawn.
    airframe = airframe_of(Path(f"{name}.json"), raw)
    effects = {
        "rate_damping_N_m_s_rad": [inflow_damping(airframe, 0), inflow_damping(airframe, 1),
                                   rotor_drag_damping_yaw(airframe)],
        "rotor_inertia_kg_m2": motor_torque_bound(airframe),
        "esc_delay_ticks": int(rng.integers(ranges.esc_delay_ticks[0], ranges.esc_delay_ticks[1] + 1)),
        "gyro_delay_ticks": int(rng.integers(ranges.gyro_delay_ticks[0], ranges.gyro_delay_ticks[1] + 1)),
        "gyro_noise_std_rad_s": float(rng.uniform(*ranges.gyro_noise_std_rad_s)),
        "esc_telemetry_delay_ticks": int(rng.integers(ranges.esc_telemetry_delay_ticks[0],
                                                      ranges.esc_telemetry_delay_ticks[1] + 1)),
        "esc_telemetry_loss_fraction": float(rng.uniform(*ranges.esc_telemetry_loss)),
    }
    source = {key: _EFFECT_SOURCES.get(key, "Drawn over the range.") for key in effects}
    return {**raw, "effects": {key: {"value": v, "source": source[key]} for key, v in effects.items()}}


def draw_airframes(seed: int, count: int, ranges: AirframeRanges = AirframeRanges()) -> list[dict[str, Any]]:
    """`count` airframes of draw `seed`, named drawn_<seed>_<i>: the same seed, the same files."""
    rng = np.random.default_rng(seed)
    return [draw_airframe(rng, f"drawn_{seed}_{i}", ranges) for i in range(count)]


DRAW_PREFIX = "draw:"


def airframe_pool(value: str) -> tuple[Airframe, ...]:
    """The airframes `value` names: `draw:COUNT:SEED` (`draw_airframes`, nothing written), or a folder of
    airframe files (every *.json in it but randomisation ranges), or files separated by commas."""
    if value.startswith(DRAW_PREFIX):
        parts = value[len(DRAW_PREFIX):].split(":")
        try:
            count, seed = (int(p) for p in parts)
        except ValueError:
            raise UserError(f"airframe pool {value!r}: draw:COUNT:SEED, two integers") from None
        if count < 1:
            raise UserError(f"airframe pool {value!r}: COUNT must be at least 1")
        return tuple(airframe_of(Path(f"{raw['name']}.json"), raw) for raw in draw_airframes(seed, count))
    folder = Path(value)
    if folder.is_dir():
        files = sorted(p for p in folder.glob("*.json") if not p.name.endswith(".randomization.json"))
        if not files:
            raise UserError(f"airframe pool {value!r}: no airframe files (*.json) in the folder")
    else:
        files = [Path(p) for p in value.split(",") if p]
    return tuple(load_airframe(f) for f in files)


def figures(raw: dict[str, Any]) -> dict[str, Any]:
    """What a drawn file is, in the ranges' terms: mass, thrust-to-weight, arm, motor lags, delays."""
    a = airframe_of(Path(f"{raw['name']}.json"), raw)
    return {"name": a.name, "mass_kg": round(a.mass, 4), "thrust_to_weight": round(a.thrust_to_weight(), 3),
            "arm_m": round(float(np.hypot(*a.rotor_positions[0, :2])), 4),
            "motor_tau_up_s": round(a.motor.tau_up, 4), "motor_tau_down_s": round(a.motor.tau_down, 4),
            "esc_delay_ticks": a.esc_delay_ticks, "gyro_delay_ticks": a.gyro_delay_ticks}


def draw_command(args: Any) -> int:
    """`fcemu twin draw`: the draw's airframe files in --out, a line (or a JSON object) each."""
    if args.count < 1:
        raise UserError(f"--count must be at least 1, got {args.count}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    drawn = []
    for raw in draw_airframes(args.seed, args.count):
        path = out / f"{raw['name']}.json"
        path.write_text(json.dumps(raw, indent=2) + "\n", encoding="utf-8")
        drawn.append({**figures(raw), "file": str(path)})
    if args.json:
        print(json.dumps({"seed": args.seed, "airframes": drawn}))
    else:
        for f in drawn:
            print(f"{f['file']}: {f['mass_kg'] * 1000:.0f} g, thrust-to-weight {f['thrust_to_weight']:.1f}, "
                  f"arm {f['arm_m'] * 1000:.0f} mm, motor lag {f['motor_tau_up_s'] * 1000:.0f}/"
                  f"{f['motor_tau_down_s'] * 1000:.0f} ms, ESC {f['esc_delay_ticks']} + gyro "
                  f"{f['gyro_delay_ticks']} ticks late")
    return 0


_SOURCES = {
    "base_mass_kg": "Drawn log-uniform over the range.",
    "base_inertia_kg_m2": "Roll: mass × arm² × a drawn share; pitch 0.9-1.2 × roll; yaw 0.8-1.0 × their sum.",
    "rotor_radius_m": "0.40-0.62 of the arm: clear of the neighbouring prop, √2 arms away.",
    "motors": "A true X at the drawn arm, Betaflight's Quad X order and default spins ('props in').",
    "motor.max_rotor_speed_rad_s": "A drawn tip speed over the radius.",
    "motor.thrust_coefficient_N_per_rad_s2": "The drawn thrust-to-weight × weight / (4 × top speed²).",
    "motor.moment_constant_m": "The radius × a drawn drag-to-thrust share.",
    "motor.time_constant_up_s": "Drawn log-uniform over the range.",
    "motor.time_constant_down_s": "1-1.6 × the spin-up lag.",
}
_EFFECT_SOURCES = {
    "rate_damping_N_m_s_rad": "Roll and pitch: rotor inflow by momentum theory; yaw: PX4's Iris rotor drag "
                              "scaled by the radius cubed (sim_bridge.relative_ranges).",
    "rotor_inertia_kg_m2": "What the motor's torque lets its lag spin up (sim_bridge.relative_ranges).",
}
