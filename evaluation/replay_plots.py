"""`fcemu replay`'s plots: the log and the twin side by side, and their step responses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fcemu.evaluation.identify import AXES
from fcemu.evaluation.replay import AxisComparison, Flown


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_replay(flown: Flown, title: str, path: Path, window_s: float = 3.0) -> Path:
    """Per axis the setpoint, the log's gyro and the twin's over the `window_s` with the most stick."""
    plt = _pyplot()
    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True)
    n = max(1, round(window_s / (flown.t[1] - flown.t[0])))
    activity = np.convolve(np.abs(np.diff(flown.setpoint, axis=0)).sum(axis=1), np.ones(n), mode="valid")
    start = int(np.argmax(activity)) if len(activity) else 0
    part = slice(start, start + n)
    t = flown.t[part]
    for i, ax in enumerate(axes[:3]):
        ax.plot(t, flown.setpoint[part, i], color="0.6", lw=1.0, label="setpoint")
        ax.plot(t, flown.log_gyro[part, i], color="k", lw=1.1, label="log")
        ax.plot(t, flown.twin_gyro[part, i], color="tab:blue", lw=1.0, label="twin")
        ax.set_ylabel(f"{AXES[i]} rad/s")
        ax.grid(alpha=0.3)
    axes[3].plot(t, flown.log_command[part].mean(axis=1), color="k", lw=1.0, label="log")
    axes[3].plot(t, flown.twin_command[part].mean(axis=1), color="tab:blue", lw=1.0, label="twin")
    axes[3].set_ylabel("mean motor 0..1")
    axes[3].set_xlabel("s into the replayed stretch")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[3].grid(alpha=0.3)
    fig.suptitle(f"{title}: the log and its twin on the same setpoints")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_steps(axes: dict[str, AxisComparison], title: str, path: Path) -> Path:
    plt = _pyplot()
    fig, panels = plt.subplots(1, 3, figsize=(12, 3.8), sharey=True)
    for ax, (axis, c) in zip(panels, axes.items(), strict=True):
        for step, label, color in ((c.log_step, "log", "k"), (c.twin_step, "twin", "tab:blue")):
            if step is not None:
                ax.plot(step.t_s * 1e3, step.response, color=color,
                        label=f"{label}: peak {step.peak:.2f}, rise {step.rise_ms:.1f} ms")
        ax.axhline(1.0, color="0.7", lw=0.8)
        ax.set_title(axis)
        ax.set_xlabel("ms after a step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    panels[0].set_ylabel("response (1 = the step)")
    fig.suptitle(f"{title}: step responses (setpoint → gyro, Wiener deconvolution)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
