"""The step responses a pilot looks at, for `fcemu tune`'s and `fcemu fit`'s reports: per axis the
held-out command of median size on that axis, its setpoint and each controller's rate.

`evaluation.report.plot_step_responses` draws one command on every axis for `fcemu eval`; a tune
or a fit is judged per axis, so here each axis gets the command typical of it, chosen from the
commands alone so that a tune needs to fly only those few again.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from fcemu.evaluation.metrics import AXES, SETTLE_S, SUCCESS_BAND, traces_episode_metrics
from fcemu.sitl.traces import Traces

SHOWN_BEFORE_STEP_S = 0.05  # of an in-flight episode's warm-up, so the step is seen leaving hover


def representative_commands(commands: np.ndarray) -> list[int]:
    """Per axis (roll, pitch, yaw), the index of the command of median size on that axis."""
    size = np.abs(np.asarray(commands, dtype=float))
    order = np.argsort(size, axis=0, kind="stable")
    return [int(order[(len(size) - 1) // 2, axis]) for axis in range(len(AXES))]


def commands_of(traces: Traces) -> np.ndarray:
    """(N, 3) each episode's command: its setpoint once the step is on."""
    return traces.setpoint[:, -1, :]


def _label(name: str, traces: Traces, episode: int, axis: int) -> str:
    ep, _ = traces_episode_metrics(traces.episode(episode))
    rise, peak = ep.rise_ms[0, axis], ep.peak_pct[0, axis]
    parts = [f"Error {ep.error[0, axis]:.1f}"]
    if np.isfinite(rise):
        parts.append(f"rise {rise:.0f} ms")
    if np.isfinite(peak):
        parts.append(f"peak {peak:.0f} %")
    return f"{name}: {', '.join(parts)}"


def plot_steps(rows: Mapping[str, Mapping[str, Traces]], path: str | os.PathLike[str], title: str,
               episodes: Sequence[int] | None = None) -> Path:
    """A row per task (label → controller label → its traces, every controller's on the same commands),
    a column per axis: that axis's setpoint, the band Success judges (±10 % of the step from 0.5 s on),
    each controller's rate with its Error, Rise and Peak on that axis.
    `episodes`, per axis, names the episode drawn; by default `representative_commands`."""
    from matplotlib.figure import Figure

    if not rows or not all(rows.values()):
        raise ValueError("plot_steps: no traces to draw")
    fig = Figure(figsize=(13, 3.4 * len(rows) + 0.6), layout="constrained")
    panels = np.atleast_2d(fig.subplots(len(rows), len(AXES), squeeze=False))
    for r, (task, flown) in enumerate(rows.items()):
        first = next(iter(flown.values()))
        for name, traces in flown.items():
            if not np.array_equal(traces.setpoint, first.setpoint):
                raise ValueError(f"plot_steps: {name} flew other commands than {next(iter(flown))} ({task})")
        chosen = list(episodes) if episodes is not None else representative_commands(commands_of(first))
        shown = first.t >= -SHOWN_BEFORE_STEP_S - 1e-9
        t_ms = first.t[shown] * 1e3
        for a, axis in enumerate(AXES):
            ax, i = panels[r, a], chosen[a]
            sp = first.setpoint[i, shown, a]
            e0 = abs(sp[-1] - first.step_window().rate[i, 0, a])
            ax.plot(t_ms, sp, "k--", lw=1.2, label="setpoint")
            ax.fill_between(t_ms, sp - SUCCESS_BAND * e0, sp + SUCCESS_BAND * e0, color="0.85", lw=0,
                            where=first.t[shown] >= SETTLE_S - 1e-9, label="Success's band")
            for name, traces in flown.items():
                ax.plot(t_ms, traces.rate[i, shown, a], lw=1.3, label=_label(name, traces, i, a))
            command = ", ".join(f"{v:.2f}" for v in commands_of(first)[i])
            ax.set_title(f"{task}: {axis}\nΩ* = [{command}] rad/s", fontsize=9)
            ax.set_xlabel("ms after the step")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="best")
        panels[r, 0].set_ylabel("rate (rad/s)")
    fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=100)
    return path
