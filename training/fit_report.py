"""DIR/report.md of `fcemu fit`: the bar's lines for the policy against the tuned PID, and the times."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fcemu.evaluation.bar import SMOOTHNESS_BAR
from fcemu.evaluation.metrics import AXES, EvalMetrics
from fcemu.training.fit_options import FitOptions, shipped_pid
from fcemu.training.options import command_line as options_command_line

STEP_PLOT = "step_response.png"


def metrics_json(m: EvalMetrics) -> dict[str, Any]:
    """The figures fit.json keeps of one controller's flights."""
    out = {k: {a: round(m.stat(k, a).mean, 2) for a in AXES} for k in ("error", "rise_ms", "peak_pct",
                                                                     "success_pct")}
    out["error_sum"] = round(sum(out["error"].values()), 2)
    out["smoothness"] = round(m.stat("smoothness", "roll").mean, 3)
    return out


def _axes(values: dict[str, float], fmt: str = ".1f") -> str:
    return " / ".join(format(values[a], fmt) for a in AXES)


def _mark(ok: bool | None) -> str:
    return "not judged" if ok is None else ("met" if ok else "**not met**")


def task_table(name: str, task: dict[str, Any]) -> list[str]:
    pol, pid, bar = task["policy"], task["pid"], task["bar"]
    checks = bar["checks"]
    bound = "" if bar["times_bound"] is None else f", {bar['times_bound']:.3f} × the bound"
    error_marks = _mark(checks["error_ratio"]) + ("" if checks["times_bound"] is None
                                                  else ", " + _mark(checks["times_bound"]))
    rise = bar["rise_ms_policy_pid_ci95"]
    return [
        f"### {name}", "",
        "| line | policy | tuned PID | verdict |", "|---|---|---|---|",
        f"| Error sum (≤ 0.95 × PID{', ≤ 1.2 × bound' if bar['bound_sum'] else ''}) | {pol['error_sum']:.1f} "
        f"({bar['error_ratio']:.3f} ×{bound}) | {pid['error_sum']:.1f} | "
        f"{error_marks} |",
        f"| Error r / p / y | {_axes(pol['error'])} | {_axes(pid['error'])} | |",
        f"| Rise ms r / p / y (≤ PID + the 95 % interval) | {_axes(pol['rise_ms'])} | "
        f"{_axes(pid['rise_ms'])} "
        f"(± {' / '.join(f'{rise[a][2]:.1f}' for a in AXES)}) | {_mark(checks['rise'])} |",
        f"| Peak % (≤ PID + 3) | {_axes(pol['peak_pct'])} | {_axes(pid['peak_pct'])} | "
        f"{_mark(checks['peak'])} |",
        f"| Success % (≥ 99.8, or the PID's) | {_axes(pol['success_pct'])} | {_axes(pid['success_pct'])} | "
        f"{_mark(checks['success'])} |",
        f"| motors µs/step (≤ {SMOOTHNESS_BAR:g} × PID) | {pol['smoothness']:.2f} "
        f"({bar['smoothness_ratio']:.2f} ×) | "
        f"{pid['smoothness']:.2f} | {_mark(checks['smoothness'])} |", ""]


def teacher_speed(student: dict[str, Any]) -> str:
    """Which time constant the teacher closed the rate error with, and how it was chosen."""
    speed = student.get("speed")
    if speed is None:
        return f"`{student['teacher']}`, its time constant given."
    flown = ", ".join(f"{f['lag_multiple']:g} lags: Error {f['error_sum']:.1f}, motors {f['smoothness']:.2f}"
                      for f in speed["flown"])
    students = "; ".join(f"the student of {f['lag_multiple']:g} lags: motors {f['student_smoothness']:.2f}"
                         for f in speed.get("tried", []))
    return (f"time constant {speed['lag_multiple']:g} motor lags: of the teachers flown alone on "
            f"{speed['commands']} tuning commands ({flown}; the PID {speed['pid_smoothness']:.2f} µs/step, "
            f"Error {speed['pid_error_sum']:.1f}), the fastest-tracking whose student's motors stay within "
            f"{SMOOTHNESS_BAR:g} × the PID's there ({students}).{teacher_shape(speed)}")


def teacher_shape(speed: dict[str, Any]) -> str:
    """The share of yaw the teacher served first and its braking share, and the shapes flown for them."""
    from fcemu.training.inversion_teacher import BRAKING_SHARE

    flown = "; ".join(f"{f['yaw_first']:g} of yaw first, braking {f['braking']:g}: Error {f['error_sum']:.1f}"
                      + ("" if f["admitted"] else " (not admitted)") for f in speed.get("shapes", []))
    chosen = (f" Shape: {speed.get('yaw_first', 0.0):g} of yaw's need served first, braking "
              f"{speed.get('braking', BRAKING_SHARE):g}")
    chosen = (chosen + "." if not flown else f"{chosen}, of those flown at that speed ({flown}) the least "
              "Error admitted, where it beats the speed stage's by more than 1 %.")
    return chosen + damping_line(speed)


def damping_line(speed: dict[str, Any]) -> str:
    """The teacher's damping ratio, and the more damped shape flown for it."""
    from fcemu.training.inversion_teacher import DAMPING

    line = f" Damping {speed.get('damping', DAMPING):g}"
    flown = speed.get("dampings", [])
    if not flown:
        return line + "."
    f = flown[0]
    return (f"{line}: at {f['damping']:g}, Error {f['error_sum']:.1f}, highest Peak "
            f"{max(f['peak_pct']):.1f} %"
            + ("" if f["admitted"] else " (not admitted)") + "; the more damped is taken where admitted, "
            "within 1 % of the shape's Error, with a lower highest Peak.")


def write_report(summary: dict[str, Any], path: Path) -> None:
    check, times, student = summary["check"], summary["time_s"], summary["student"]
    verdict = "meets the bar" if summary["meets_bar"] else "does not meet the bar"
    tune = summary["tune"]
    lines = [
        f"# `fcemu fit` for {summary['airframe']}", "",
        "```", summary["command"], "```", "",
        f"The policy ({student['inputs']} inputs, {'-'.join(map(str, student['net_arch']))} tanh, fitted by "
        f"DAgger to the model-based teacher `{student['teacher']}`) **{verdict}** against the PID tuned "
        f"here, on {check['episodes']} held-out commands (seed {check['seed']}).", "",
        f"- PID: `{summary['pid']}` — "
        + (f"given (`--pid {tune['given']}`), not tuned here." if tune["given"] else
           f"the tune's lines {'met' if tune['meets_lines'] else 'not met: ' + '; '.join(tune['fails'])}."),
        f"- Policy: `{summary['policy']}`.",
        f"- Teacher: {teacher_speed(student)}",
        f"- Lower bound on the Error (`fcemu bound`, from rest): "
        f"{'not available' if check['bound_sum'] is None else format(check['bound_sum'], '.1f')}.",
        "- STM32F405 at 168 MHz (`fcemu bench mcu`, ≤ 250 µs): "
        + (f"{check['mcu_us_f405']:.1f} µs." if check["mcu_us_f405"] is not None
           else f"{check['mcu_note']}."),
        ""]
    for name, title in (("episodic", "From rest (episodic)"), ("inflight", "In flight, from hover")):
        lines += task_table(title, check["tasks"][name])
    if check.get("step_plot"):
        lines += ["### Step responses", "",
                  "Per axis, the held-out command of median size on that axis, from rest and in flight: its "
                  "setpoint, the ±10 % band Success judges from 0.5 s on, the PID's rate and the "
                  "policy's.", "", f"![Step responses: the policy and the PID]({check['step_plot']})", ""]
    lines += ["## Time", "", "| tune (bound included) | teacher's speed | policy | check | total |",
              "|---:|---:|---:|---:|---:|",
              f"| {times['tune']:.0f} s | {times.get('teacher', 0.0):.0f} s | {times['policy']:.0f} s | "
              f"{times['check']:.0f} s | {times['total']:.0f} s |", "",
              "## Fly it", "", "```",
              f"fcemu sitl --airframe {summary['airframe']} --controller {summary['policy']}"
              "   # its PID, named in its metadata, is its fallback",
              f"fcemu eval --airframe {summary['airframe']} --controller {summary['policy']} "
              f"--controller pid:{summary['pid']}",
              "```", ""]
    path.write_text("\n".join(lines))


def command_line(opts: FitOptions) -> str:
    """The `fcemu fit` command that makes the same fit (in fit.json and the report): its options, and
    `--tune` where it tuned a PID although the airframe's ships."""
    tuned_anew = opts.pid is None and shipped_pid(opts.airframe) is not None
    return options_command_line("fcemu fit", opts) + (" --tune" if tuned_anew else "")
