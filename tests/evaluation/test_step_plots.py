"""The step responses `fcemu tune` and `fcemu fit` draw: per axis the command of median size on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation.step_plots import plot_steps, representative_commands
from fcemu.sitl.traces import Traces

pytestmark = pytest.mark.no_wall_clock


def _traces(commands: np.ndarray, lag_s: float, task: str = "episodic") -> Traces:
    """A first-order answer to each command, at rest before the step (0.1 s of it in flight)."""
    t = np.arange(-0.1 if task == "inflight" else 0.0, 1.0, 0.001)
    on = (t >= 0)[None, :, None]
    setpoint = np.where(on, commands[:, None, :], 0.0)
    rate = setpoint * (1 - np.exp(-np.maximum(t, 0) / lag_s))[None, :, None]
    return Traces(t, setpoint, rate, np.full((*rate.shape[:2], 4), 1500.0), task=task)


def test_each_axis_gets_the_command_of_median_size_on_it() -> None:
    commands = np.array([[0.1, -3.0, 0.5], [-2.0, 0.2, 0.4], [0.5, 1.0, -0.1], [4.0, 0.1, 2.0],
                         [1.0, 0.6, 0.3]])
    # sizes: roll 0.1 2 0.5 4 1, median 1 (row 4); pitch 3 0.2 1 0.1 0.6, 0.6 (row 4);
    # yaw 0.5 0.4 0.1 2 0.3, 0.4 (row 1)
    assert representative_commands(commands) == [4, 4, 1]


def test_the_plot_is_written_for_every_task_and_refuses_controllers_on_other_commands(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    commands = rng.uniform(-3, 3, (7, 3))
    rows = {task: {"PID": _traces(commands, 0.05, task), "policy": _traces(commands, 0.03, task)}
            for task in ("episodic", "inflight")}
    path = plot_steps(rows, tmp_path / "steps.png", "test")
    assert path.read_bytes().startswith(b"\x89PNG") and path.stat().st_size > 10_000
    rows["inflight"]["policy"] = _traces(commands[::-1].copy(), 0.03, "inflight")
    with pytest.raises(ValueError, match="policy flew other commands than PID"):
        plot_steps(rows, tmp_path / "other.png", "test")
    with pytest.raises(ValueError, match="no traces"):
        plot_steps({}, tmp_path / "none.png", "test")
