"""Markdown evaluation report: the paper's Table "best" with our controllers beside its
figures, plus step-response and continuous-task PNGs.

Takes already-computed metrics and traces; it never runs a simulation. Figures use
matplotlib's Figure API (Agg canvas) directly, so the process-wide backend is untouched.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure

from fcemu.evaluation.metrics import AXES, MIN_E0, SETTLE_S, EvalMetrics, Stat
from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME
from fcemu.sitl.traces import Traces

if TYPE_CHECKING:
    from fcemu.evaluation.faults import FaultResult
    from fcemu.evaluation.perturb import PerturbedResult

PAPER_COLUMNS = ("PPO m=1", "PID")
CONTINUOUS_SECONDS = 10.0
_AXIS_SYMBOL = {"roll": "roll (φ)", "pitch": "pitch (θ)", "yaw": "yaw (ψ)"}
_MOTOR_LABELS = ("m1 rear-right", "m2 front-right", "m3 rear-left", "m4 front-left")

# (row label, our metric attribute, paper table, paper key, decimals)
_ROWS: tuple[tuple[str, str, str | None, str | None, int], ...] = (
    ("Rise (ms)", "rise_ms", "best_vs_pid", "rise_ms", 1),
    ("Peak (%)", "peak_pct", "best_vs_pid", "peak_pct", 1),
    ("Error (rad/s)", "error", "best_vs_pid", "error_rad_s", 1),
    ("Stability (rad/s²)", "stability", "best_vs_pid", "stability", 2),
    ("Success (%)", "success_pct", "success_failure", "success_pct", 1),
    ("Failure (%) ¹", "failure_pct", None, None, 1),
    ("Failure, paper's averaging (%) ²", "failure_all_pct", "success_failure", "failure_pct", 1),
    ("Smoothness (µs/step) ³", "smoothness", None, None, 2),
)


@dataclass(frozen=True)
class ControllerResult:
    """One evaluated controller: its metrics and the traces to draw."""

    name: str
    metrics: EvalMetrics
    step: Traces | None = None  # episodic-task traces; one episode is drawn
    continuous: Traces | None = None  # continuous-task traces; episode 0, first 10 s, is drawn
    perturbed: PerturbedResult | None = None  # the same commands on perturbed airframes
    faults: tuple[FaultResult, ...] = ()  # the same commands with a fault injected (--fault)


def load_paper_tables() -> dict[str, Any]:
    """The paper's result tables as shipped in `evaluation/data/paper_tables.json`."""
    text = resources.files("fcemu.evaluation").joinpath("data/paper_tables.json").read_text(encoding="utf-8")
    return json.loads(text)


def _fmt(mean: float | None, ci: float | None, decimals: int) -> str:
    if mean is None or not np.isfinite(mean):
        return "—"
    ci_text = "—" if ci is None or not np.isfinite(ci) else f"{ci:.{decimals}f}"
    mean_text = f"{mean:.{decimals}f}"
    if mean_text.startswith("-") and not mean_text.strip("-0."):
        mean_text = mean_text[1:]  # "-0.00" reads as a sign where there is none
    return f"{mean_text} ± {ci_text}"


def _cell_name(name: str) -> str:
    return name.replace("|", r"\|")


def table_best(results: Sequence[ControllerResult], paper: dict[str, Any] | None = None) -> str:
    """Markdown table: rows metric × axis; columns our controllers, then the paper's figures."""
    tables = (paper or load_paper_tables())["tables"]
    header = ["Metric", "Axis", *(_cell_name(r.name) for r in results),
              *(f"{c} (paper)" for c in PAPER_COLUMNS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * 2 + "---:|" * (len(header) - 2)]
    for label, attr, table, key, dec in _ROWS:
        for axis in AXES:
            cells = [label, _AXIS_SYMBOL[axis]]
            for r in results:
                s: Stat = getattr(r.metrics.axis(axis), attr)
                cells.append(_fmt(s.mean, s.ci95, dec))
            for col in PAPER_COLUMNS:
                if table is None or key is None:
                    cells.append("n/a")
                else:
                    mean, ci = tables[table][col][key][axis]
                    cells.append(_fmt(mean, ci, 1))  # the paper prints one decimal
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _counts_table(results: Sequence[ControllerResult]) -> str:
    lines = [f"| Controller | Axis | units | e0 below {MIN_E0} rad/s | no settling window | failures "
             "| 90% never reached |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in results:
        for axis in AXES:
            a = r.metrics.axis(axis)
            lines.append(f"| {_cell_name(r.name)} | {axis} | {a.n_episodes} | {a.n_excluded} | "
                         f"{a.n_unassessed} | {a.n_failures} | {a.n_rise_not_reached} |")
    return "\n".join(lines)


def _motor_table(results: Sequence[ControllerResult]) -> str:
    lines = ["| Controller | " + " | ".join(_MOTOR_LABELS) + " |", "|---|" + "---:|" * 4]
    for r in results:
        cells = [_fmt(s.mean, s.ci95, 2) for s in r.metrics.smoothness_per_motor]
        lines.append(f"| {_cell_name(r.name)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _axes_cell(m: EvalMetrics, metric: str, decimals: int = 1) -> str:
    values = (m.stat(metric, a).mean for a in AXES)
    return "/".join("—" if not np.isfinite(v) else f"{v:.{decimals}f}" for v in values)


def _error_sum(m: EvalMetrics) -> float:
    return sum(m.stat("error", a).mean for a in AXES)


def robustness_table(results: Sequence[ControllerResult]) -> str:
    """Nominal against perturbed per controller: Error (Σ over axes), Success, Peak, Rise, smoothness."""
    lines = ["| Controller | airframes | Error Σ | Error Σ, worst airframe | Success % r/p/y | Peak % r/p/y "
             "| Rise ms r/p/y | Smoothness µs/step |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        if r.perturbed is None:
            continue
        p = r.perturbed
        worst = f"{float(np.max(p.error_sum)):.1f}"
        rows = (("nominal", r.metrics, "—"), (f"{len(p.airframes)} perturbed", p.metrics, worst))
        for label, m, worst_cell in rows:
            smooth = m.stat("smoothness", "roll")
            lines.append(f"| {_cell_name(r.name)} | {label} | {_error_sum(m):.1f} | {worst_cell} | "
                         f"{_axes_cell(m, 'success_pct')} | {_axes_cell(m, 'peak_pct')} | "
                         f"{_axes_cell(m, 'rise_ms')} | {_fmt(smooth.mean, smooth.ci95, 2)} |")
    return "\n".join(lines)


def delay_table(results: Sequence[ControllerResult]) -> str:
    """The perturbed airframes grouped by loop delay, per controller ("" when no delay was drawn)."""
    lines = ["| Controller | delay (ticks) | airframes | Success % r/p/y | Error Σ |",
             "|---|---|---:|---:|---:|"]
    for r in results:
        for g in r.perturbed.by_delay() if r.perturbed is not None else ():
            lines.append(f"| {_cell_name(r.name)} | {g.label} | {g.airframes} | "
                         f"{_axes_cell(g.metrics, 'success_pct')} | {g.error_sum:.1f} |")
    return "\n".join(lines) if len(lines) > 2 else ""


def _delay_section(results: Sequence[ControllerResult]) -> list[str]:
    table = delay_table(results)
    if not table:
        return []
    return ["The same airframes grouped by each drawn loop delay (an airframe counts once under "
            "its ESC delay and once under its gyro delay):", "", table, ""]


def plot_robustness(results: Sequence[ControllerResult], path: str | os.PathLike[str]) -> Path:
    """Per-airframe Error Σ per controller (box and points), the nominal airframe's as a red diamond."""
    drawn = [r for r in results if r.perturbed is not None]
    if not drawn:
        raise ValueError("plot_robustness: no controller was flown on perturbed airframes")
    fig = Figure(figsize=(max(5.0, 2.2 * len(drawn) + 2), 5), layout="constrained")
    ax = fig.subplots()
    data = [r.perturbed.error_sum for r in drawn if r.perturbed is not None]
    ax.boxplot(data, widths=0.5, showfliers=False)
    jitter = np.random.default_rng(0)
    for i, values in enumerate(data, start=1):
        ax.plot(i + jitter.uniform(-0.12, 0.12, len(values)), values, "o", ms=4, alpha=0.7, color="tab:blue",
                label="perturbed airframe" if i == 1 else None)
    ax.plot(range(1, len(drawn) + 1), [_error_sum(r.metrics) for r in drawn], "D", ms=8, color="tab:red",
            label="nominal airframe")
    ax.set_xticks(range(1, len(drawn) + 1), [Path(r.name).name for r in drawn])
    ax.set_ylabel("Error Σ over axes (rad/s), mean per command")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(loc="best", fontsize=8)
    n = len(drawn[0].perturbed.airframes) if drawn[0].perturbed is not None else 0
    fig.suptitle(f"Error on {n} perturbed airframes, same commands")
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def plot_step_responses(results: Sequence[ControllerResult], path: str | os.PathLike[str],
                        episode: int = 0) -> Path:
    """One command, every controller: a subplot per axis, setpoint dashed, ±10% band red dashed."""
    drawn = [r for r in results if r.step is not None]
    if not drawn:
        raise ValueError("plot_step_responses: no controller has step traces")
    ref = drawn[0].step
    assert ref is not None
    for r in drawn[1:]:
        assert r.step is not None
        if r.step.setpoint.shape[1] != ref.setpoint.shape[1] or not np.allclose(
                r.step.setpoint[episode], ref.setpoint[episode]):
            raise ValueError(f"plot_step_responses: {r.name} saw a different command than {drawn[0].name}; "
                             "evaluate controllers with the same seed")
    t_ms = (ref.t - ref.t[0]) * 1000.0
    sp = ref.setpoint[episode]
    fig = Figure(figsize=(9, 8), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for i, (ax, axis) in enumerate(zip(axes, AXES, strict=True)):
        e0 = sp[0, i] - ref.rate[episode, 0, i]
        ax.plot(t_ms, sp[:, i], "k--", lw=1.2, label="setpoint Ω*")
        ax.plot(t_ms, sp[:, i] + 0.1 * abs(e0), "r--", lw=0.8, label="±10% of e0")
        ax.plot(t_ms, sp[:, i] - 0.1 * abs(e0), "r--", lw=0.8)
        for r in drawn:
            assert r.step is not None
            ax.plot(t_ms, r.step.rate[episode, :, i], lw=1.2, label=r.name)
        ax.set_ylabel(f"{axis} (rad/s)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time (ms)")
    target = ", ".join(f"{v:.2f}" for v in sp[0])
    fig.suptitle(f"Step response, Ω* = [{target}] rad/s")
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def plot_continuous(result: ControllerResult, path: str | os.PathLike[str],
                    seconds: float = CONTINUOUS_SECONDS) -> Path:
    """The first `seconds` of continuous-task episode 0: rates vs setpoints per axis, motor outputs."""
    tr = result.continuous
    if tr is None:
        raise ValueError(f"plot_continuous: {result.name} has no continuous-task traces")
    t = tr.t - tr.t[0]
    n = int(np.searchsorted(t, seconds, side="right"))
    t = t[:n]
    fig = Figure(figsize=(11, 9), layout="constrained")
    axes = fig.subplots(4, 1, sharex=True)
    for i, (ax, axis) in enumerate(zip(axes[:3], AXES, strict=True)):
        ax.plot(t, tr.setpoint[0, :n, i], "k-", lw=1.0, label="setpoint Ω*")
        ax.plot(t, tr.rate[0, :n, i], "r-", lw=0.9, label="rate Ω")
        ax.set_ylabel(f"{axis} (rad/s)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    for m, label in enumerate(_MOTOR_LABELS):
        axes[3].plot(t, tr.pwm[0, :n, m], lw=0.7, label=label)
    axes[3].set_ylabel("PWM (µs)")
    axes[3].set_xlabel("time (s)")
    axes[3].legend(loc="upper right", fontsize=7, ncols=4)
    axes[3].grid(alpha=0.3)
    fig.suptitle(f"Continuous task, {result.name}, {t[-1]:.1f} s")
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(name).name).strip("_.") or "controller"


_NOTES = f"""\
Metrics follow docs/DESIGN.md, per axis; e0 = Ω*(0) − Ω(0). Axes with |e0| < {MIN_E0} rad/s are
left out of Success, Failure, Rise and Peak (counted under "What was left out"). CIs are
1.96·σ/√n, σ the sample standard deviation; "—" means undefined (no contributing episode, or
n < 2 for the CI).

- Success: mean |Ω* − Ω| over t ≥ {SETTLE_S} s within 10% of |e0|. The paper says "eventually settles
  in the ±10% band"; DESIGN.md's mean-error form is used here.
- ¹ Failure: that mean as % of |e0|, averaged over the failing episodes only (DESIGN.md);
  0.0 ± 0.0 when nothing fails. The paper's figures are not comparable with it: PPO m=1 roll
  (99.8% success, failure 0.1%) is only consistent with an average over *all* episodes,
  successes counted as 0, which is the next row.
- ² Failure, paper's averaging: the failing episodes' error %, successes as 0, over all episodes.
- Rise: first crossings of 10% and 90% of e0 corrected, interpolated between 1 ms samples;
  episodes that never reach 90% are left out and counted.
- Peak: max of (Ω − Ω(0))/e0; Error: Σ|Ω* − Ω| over the episode (1000 steps in the episodic task).
- Stability: least-squares slope of Ω over t ≥ {SETTLE_S} s. The paper prints one decimal.
- ³ Smoothness: mean |Δpwm| between consecutive 1 ms steps, over all four motors (µs/step); not
  an axis quantity, so every axis row shows the same value; per-motor values below. Not in the paper.
- Continuous task: each command hold is evaluated as an episode of its own (e0 at the hold's start,
  Error summed over the hold); holds shorter than {SETTLE_S} s have no settling window (counted) and
  no Stability.
"""


def write_report(
    out_dir: str | os.PathLike[str],
    results: Sequence[ControllerResult],
    *,
    command: str,
    seed: int | None,
    task: str = "episodic",
    episodes: int | None = None,
    step_episode: int = 0,
    title: str = "fcemu evaluation",
    airframe: str = DEFAULT_AIRFRAME,
    twin: str | None = None,
) -> Path:
    """Write `report.md` and its PNGs into out_dir (created); returns the Markdown path.

    `airframe`: the airframe the firmware is set up for (a name under sim_bridge/airframes or a
    path); `twin`: the one the twin flies where it is another (`fcemu eval --twin`).
    """
    if not results:
        raise ValueError("write_report: no results")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_text = episodes if episodes is not None else results[0].metrics.n_episodes
    parts = [
        f"# {title}",
        "",
        "```",
        command,
        "```",
        "",
        f"Seed {seed}, task {task}, airframe `{airframe}`"
        + (f" (the twin flies `{twin}`)" if twin else "")
        + f", {n_text} evaluation {results[0].metrics.unit}s "
        "per controller. "
        "Controllers evaluated with the same seed see the same commands.",
        "",
        "## Results, laid out as the paper's Table \"best\"",
        "",
        "Columns marked *(paper)* are the paper's own figures (Koch et al. 2018, Tables \"best\" "
        "and \"fails\", 2 agents × 1000 episodes), copied from `evaluation/data/paper_tables.json`, "
        "not measured here.",
        "",
        table_best(results),
        "",
        "### What was left out",
        "",
        _counts_table(results),
        "",
        "### Smoothness per motor (µs/step)",
        "",
        _motor_table(results),
        "",
        "## Figures",
        "",
    ]
    if any(r.perturbed is not None for r in results):
        first = next(r.perturbed for r in results if r.perturbed is not None)
        assert first is not None
        plot_robustness(results, out / "robustness.png")
        parts[parts.index("## Figures"):parts.index("## Figures")] = [
            "## Robustness: the same commands on perturbed airframes", "",
            f"{len(first.airframes)} airframes drawn from the randomisation ranges "
            f"(`{first.ranges or 'sim_bridge/airframes/*.randomization.json'}`) with perturb seed "
            f"{first.seed}, a stream "
            "training never draws from; perturbed rows pool every airframe's episodes. Error Σ is "
            "the mean Error per command summed over the axes.", "",
            robustness_table(results), "",
            *_delay_section(results),
            "![Error per perturbed airframe](robustness.png)", ""]
    if any(r.faults for r in results):
        from fcemu.evaluation.faults import FAULT_WINDOW, fault_table

        rows = [(r.name, f) for r in results for f in r.faults]
        parts[parts.index("## Figures"):parts.index("## Figures")] = [
            "## Faults: the same commands with a fault injected", "",
            f"Each fault comes at a seeded time between {FAULT_WINDOW[0]:.0%} and {FAULT_WINDOW[1]:.0%} of "
            "each episode (the same time for every controller). Upright: the attitude stayed within 90° of "
            "the one the commanded rates lead to from the fault on. Error Σ: from the fault tick to the "
            "episode's end, summed over the axes, mean per episode. The answer is the firmware's health "
            "monitor's (docs/DESIGN.md, \"Faults and the firmware's answers\").", "", fault_table(rows), ""]
    if any(r.step is not None for r in results):
        plot_step_responses(results, out / "step_response.png", episode=step_episode)
        parts += [f"Step response of evaluation command {step_episode}, every controller:", "",
                  "![Step responses](step_response.png)", ""]
    for i, r in enumerate(results):
        if r.continuous is None:
            continue
        name = f"continuous_{i}_{_slug(r.name)}.png"
        plot_continuous(r, out / name)
        parts += [f"Continuous task, {r.name}:", "", f"![Continuous task, {r.name}]({name})", ""]
    parts += ["## Definitions", "", _NOTES]
    path = out / "report.md"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
