"""`fcemu twin demo`: an open-loop tour of the twin, printed and plotted.

Spin up to hover in the free rig, then apply a roll, a pitch and a yaw motor
differential in the ball-joint rig. No controller: this shows the plant itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fcemu.sim_bridge.twin import Twin

AXES = ("roll", "pitch", "yaw")
# Motor differentials (Betaflight order: RR, FR, RL, FL) that push each FRD axis positive.
DIFFERENTIALS = {
    "roll": np.array([-1.0, -1.0, 1.0, 1.0]),
    "pitch": np.array([-1.0, 1.0, -1.0, 1.0]),
    "yaw": np.array([-1.0, 1.0, 1.0, -1.0]),
}


def hover_run(seconds: float = 3.0) -> dict[str, np.ndarray]:
    twin = Twin(rig="free")
    twin.reset(seed=0)
    hover = twin.airframe.hover_pwm()
    n = round(seconds / twin.dt)
    # 1.5 s spin-up ramp a little past hover to lift off, then hover PWM.
    ramp = np.minimum(np.arange(n) * twin.dt / 1.5, 1.0) * (hover + 40 - 1000) + 1000
    pwm = np.where(np.arange(n) * twin.dt < 2.0, ramp, hover)
    t, alt, climb, omega = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 4))
    for i in range(n):
        frame = twin.step(np.full(4, pwm[i]))
        truth = twin.truth()
        t[i], omega[i] = frame.t_us * 1e-6, frame.rotor_speed
        alt[i], climb[i] = -truth.position[2], -truth.velocity[2]
    return {"t": t, "altitude": alt, "climb": climb, "rotor_speed": omega, "pwm": pwm}


def differential_run(axis: str, delta_us: float = 60.0, seconds: float = 0.6) -> dict[str, np.ndarray]:
    twin = Twin(rig="rig")
    hover = twin.airframe.hover_pwm()
    twin.reset(seed=0)
    n = round(seconds / twin.dt)
    t, gyro, omega = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 4))
    for i in range(n):
        on = 0.1 <= i * twin.dt < 0.3
        frame = twin.step(hover + delta_us * DIFFERENTIALS[axis] * on)
        t[i], gyro[i], omega[i] = frame.t_us * 1e-6, frame.gyro, frame.rotor_speed
    return {"t": t, "gyro": gyro, "rotor_speed": omega}


def main(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    as_json = getattr(args, "json", False)
    say = (lambda _text: None) if as_json else print
    hover = hover_run()
    twin = Twin(rig="free")
    say(f"Iris twin: mass {twin.airframe.mass:.3f} kg, hover at {twin.airframe.hover_pwm():.0f} µs "
        f"({twin.airframe.hover_rotor_speed():.0f} rad/s per rotor)")
    say(f"free rig: spun up past hover to lift off, then hover PWM from 2 s: after {hover['t'][-1]:.1f} s "
        f"altitude {hover['altitude'][-1]:.2f} m, climb rate {hover['climb'][-1]:+.2f} m/s "
        f"(held since 2 s: {hover['climb'][2000]:+.2f} m/s)")
    summary = {"airframe": twin.airframe.name, "mass_kg": twin.airframe.mass,
               "hover_pwm_us": float(twin.airframe.hover_pwm()),
               "hover_rotor_speed_rad_s": float(twin.airframe.hover_rotor_speed()),
               "free_rig": {"seconds": float(hover["t"][-1]), "altitude_m": float(hover["altitude"][-1]),
                            "climb_m_s": float(hover["climb"][-1]),
                            "climb_at_2s_m_s": float(hover["climb"][2000])},
               "differential_us": 60.0, "differentials": {}}
    runs = {axis: differential_run(axis) for axis in AXES}
    for k, axis in enumerate(AXES):
        g = runs[axis]["gyro"]
        peak = g[np.argmax(np.abs(g[:, k])), k]
        others = np.abs(np.delete(g, k, axis=1)).max()
        summary["differentials"][axis] = {"peak_rate_rad_s": float(peak), "cross_axis_rad_s": float(others)}
        say(f"ball-joint rig, {axis} differential ±60 µs for 0.2 s: {axis} rate peaked at "
            f"{peak:+.2f} rad/s (largest cross-axis rate {others:.2f} rad/s)")

    fig, ax = plt.subplots(4, 2, figsize=(12, 11))
    ax[0, 0].plot(hover["t"], hover["altitude"])
    ax[0, 0].set_ylabel("altitude m")
    ax[0, 0].set_title("free rig: spin-up to hover")
    ax[1, 0].plot(hover["t"], hover["rotor_speed"])
    ax[1, 0].set_ylabel("rotor speed rad/s")
    ax[2, 0].plot(hover["t"], hover["pwm"])
    ax[2, 0].set_ylabel("PWM µs")
    ax[2, 0].set_xlabel("s")
    ax[3, 0].axis("off")
    for k, axis in enumerate(AXES):
        r = runs[axis]
        ax[k, 1].plot(r["t"], r["gyro"], label=["roll", "pitch", "yaw"])
        ax[k, 1].set_ylabel("rate rad/s (FRD)")
        ax[k, 1].set_title(f"ball-joint rig: {axis} differential")
        ax[k, 1].legend(loc="upper right", fontsize=8)
    r = runs["yaw"]
    ax[3, 1].plot(r["t"], r["rotor_speed"], label=["m1 RR", "m2 FR", "m3 RL", "m4 FL"])
    ax[3, 1].set_ylabel("rotor speed rad/s")
    ax[3, 1].set_title("rotor speeds during the yaw differential")
    ax[3, 1].legend(loc="lower right", fontsize=8)
    ax[3, 1].set_xlabel("s")
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    if as_json:
        print(json.dumps({**summary, "plot": str(out)}))
    else:
        print(f"plot: {out}")
    return 0
