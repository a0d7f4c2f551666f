"""`fcemu identify`'s one-page report: what was identified, how well it predicts the log's rates.

The check is a 50 ms-ahead prediction: from each measured rate, the model's acceleration
(the log's rotor speeds and rates through the fitted coefficients) integrated 50 ms on, against
the rate measured then; the base airframe's twin makes the same prediction beside it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fcemu.evaluation.identify import AXES, airframe_accel, levers, predict_ahead, prediction_fit
from fcemu.evaluation.identify_airframe import Identification
from fcemu.evaluation.rate_boxes import gyro_coefficients
from fcemu.sim_bridge.airframe import Airframe

AHEAD_S = 0.05


def predictions(ident: Identification) -> tuple[np.ndarray, np.ndarray, int]:
    """(identified (T, 3), base (T, 3), horizon in ticks): the rates predicted AHEAD_S ahead."""
    log = ident.log
    horizon = max(1, round(AHEAD_S / log.dt))
    base_accel = airframe_accel(log, ident.rates.speed, ident.base, levers(ident.base))
    return (predict_ahead(log, ident.rates.accel, horizon), predict_ahead(log, base_accel, horizon), horizon)


def plot_rates(ident: Identification, identified: np.ndarray, base: np.ndarray, path: Path,
               window_s: float = 2.0) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = ident.log
    fig, axes = plt.subplots(3, 1, figsize=(9, 7.5))
    half = round(window_s / log.dt / 2)
    for axis, ax in enumerate(axes):
        peak = int(np.argmax(np.abs(log.gyro[:, axis])))
        part = slice(max(0, peak - half), min(len(log.t), peak + half))
        ax.plot(log.t[part], log.gyro[part, axis], color="k", lw=1.2, label="measured")
        ax.plot(log.t[part], identified[part, axis], color="tab:blue", lw=1, label="identified, 50 ms ahead")
        ax.plot(log.t[part], base[part, axis], color="tab:orange", lw=1, ls="--",
                label=f"base {ident.base_label}, 50 ms ahead")
        ax.set_ylabel(f"{AXES[axis]} rad/s")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel(f"s into {log.name}")
    fig.suptitle(f"{log.name}: measured body rates against the models' 50 ms-ahead predictions")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _row(what: str, identified: str, true: float | None, unit: str = "") -> str:
    truth = "" if true is None else f" | {true:.4g}{unit}"
    return f"| {what} | {identified}{truth} |"


def write_report(ident: Identification, airframe: Airframe, airframe_path: Path, out_dir: Path,
                 truth: Airframe | None = None, flown_by: str | None = None,
                 refinement=None) -> tuple[Path, dict]:
    """DIR/report.md and DIR/rates.png; returns the report's path and its figures as JSON. `flown_by`:
    a sentence on what flew the identification flight where it says more than the log."""
    identified, base, horizon = predictions(ident)
    fit_id, fit_base = prediction_fit(ident.log, identified), prediction_fit(ident.log, base)
    plot = plot_rates(ident, identified, base, out_dir / "rates.png")
    mf, rf, log = ident.motors, ident.rates, ident.log
    m = airframe.motor
    inertia = airframe.inertia()
    true_inertia = None if truth is None else truth.inertia()

    def true(value: float | None) -> float | None:
        return None if truth is None else value

    header = "| quantity | identified (95 % interval) | true |" if truth else "| quantity | identified |"
    rule = "|---|---|---|" if truth else "|---|---|"
    rows = [header, rule,
            _row("motor time constant up", mf.tau_up.text(" s"), true(truth and truth.motor.tau_up), " s"),
            _row("motor time constant down", mf.tau_down.text(" s"), true(truth and truth.motor.tau_down),
                 " s"),
            _row("hover command", ident.hover.text(), true(truth and truth.hover_throttle())),
            _row("rotor speed at full command", f"{m.max_rotor_speed:.5g} rad/s",
                 true(truth and truth.motor.max_rotor_speed), " rad/s"),
            _row("ESC delay (ticks)", f"{airframe.esc_delay_ticks}", true(truth and truth.esc_delay_ticks)),
            _row("gyro delay (ticks)", f"{airframe.gyro_delay_ticks}",
                 true(truth and truth.gyro_delay_ticks)),
            _row("gyro noise", f"{airframe.gyro_noise_std:.4g} rad/s", true(truth and truth.gyro_noise_std),
                 " rad/s")]
    for i, name in enumerate(AXES):
        rows.append(_row(f"{name} gyro vibration", f"{airframe.gyro_vibration[i]:.4g} rad/s per (rad/s)²",
                         true(truth and truth.gyro_vibration[i]), " rad/s per (rad/s)²"))
    for i, name in enumerate(AXES):
        rows.append(_row(f"{name} gyroscopic coupling", rf.axes[i].coupling.text(),
                         None if true_inertia is None else float(gyro_coefficients(true_inertia)[i])))
    km_identified = m.km != ident.base.motor.km  # the coupling gave the yaw inertia, so k_M follows
    rows.append(_row("yaw moment constant k_M", f"{m.km:.4g} m" + ("" if km_identified else " (the base's)"),
                     true(truth and truth.motor.km), " m"))
    for i, name in enumerate(AXES):
        rows.append(_row(f"{name} effectiveness k_F/I (k_F·k_M/I on yaw)", rf.axes[i].effectiveness.text(),
                         None if truth is None else _effectiveness(truth)[i]))
        rows.append(_row(f"{name} inertia (whole airframe)", f"{inertia[i]:.4g} kg·m²",
                         None if true_inertia is None else float(true_inertia[i]), " kg·m²"))
        rows.append(_row(f"{name} rate damping", f"{airframe.rate_damping[i]:.3g} N·m·s/rad",
                         true(truth and truth.rate_damping[i]), " N·m·s/rad"))
    figures = {"log": str(log.path), "airframe": str(airframe_path), "base": ident.base_label,
               "esc_rpm": mf.from_rpm, "samples": len(log.t), "horizon_ticks": horizon,
               "prediction_fit_pct": {"identified": dict(zip(AXES, map(float, fit_id), strict=True)),
                                      "base": dict(zip(AXES, map(float, fit_base), strict=True))},
               "tau_up_s": mf.tau_up.__dict__, "tau_down_s": mf.tau_down.__dict__,
               "hover_command": ident.hover.__dict__, "props": ident.spin_note}
    refined = []
    if refinement is not None:
        figures["closed_loop"] = {"factors": refinement.factors,
                                  "gyro_delay_ticks": refinement.gyro_delay_ticks,
                                  "mismatch_before": refinement.mismatch_before,
                                  "mismatch_after": refinement.mismatch_after, "flights": refinement.flights,
                                  "stretch_s": refinement.stretch_s}
        refined = [
            "## Refined in closed loop", "",
            f"The log's own tune (`pid_log.json`) flew the twin on the log's setpoints over "
            f"{refinement.stretch_s[0]:.1f}-{refinement.stretch_s[1]:.1f} s ({refinement.flights} flights); "
            "each axis's mismatch of the rates (squared error over the log's variance) went from "
            + ", ".join(f"{a} {b:.3f} to {c:.3f}" for a, b, c in zip(AXES, refinement.mismatch_before,
                                                                    refinement.mismatch_after, strict=True))
            + ". The factors on the least-squares values: "
            + ", ".join(f"{k.replace('_', ' ')} ×{v:.3g}" for k, v in refinement.factors.items())
            + f"; gyro delay {refinement.gyro_delay_ticks} ticks. The table above is the least-squares fit; "
              "the file holds the refined numbers.", ""]
    lines = [
        f"# {airframe.name}: identified from {log.name}", "",
        f"`{airframe_path}` from `{log.path}`: {len(log.t)} samples at {1 / log.dt:.0f} Hz, motor commands "
        f"from {log.command_source}, {'with' if mf.from_rpm else 'without'} ESC rpm; base airframe "
        f"{ident.base_label}. Mass, geometry, rotor sizes and the battery are the base's (a rate log cannot "
        "give them); k_F follows from the base's mass and the hover rotor speed, roll's and pitch's inertia "
        "from k_F over the effectiveness, "
        + ("the yaw inertia from the rates' gyroscopic coupling and k_M from it" if km_identified else
           "the yaw inertia from the base's k_M (the log's rates never turned about two axes at once)")
        + ". Every number's source is in the airframe file."
        + (f" The flight was {flown_by}." if flown_by else "") + f" Motors: {ident.spin_note}.", "",
        *(f"From the log: {note}." for note in log.notes), *([""] if log.notes else []),
        *rows, "",
        f"## Body rates predicted {horizon * log.dt * 1000:.0f} ms ahead", "",
        "Fit (100 % = the measured rate; 0 % = no better than its mean):", "",
        "| model | " + " | ".join(AXES) + " |", "|---|---|---|---|",
        "| identified | " + " | ".join(f"{v:.1f} %" for v in fit_id) + " |",
        f"| base {ident.base_label} | " + " | ".join(f"{v:.1f} %" for v in fit_base) + " |", "",
        f"![measured and predicted rates]({plot.name})", "",
        *refined,
    ]
    report = out_dir / "report.md"
    report.write_text("\n".join(lines), encoding="utf-8")
    return report, figures


def _effectiveness(airframe: Airframe) -> list[float]:
    inertia, m = airframe.inertia(), airframe.motor
    return [m.kf / inertia[0], m.kf / inertia[1], m.kf * m.km / inertia[2]]
