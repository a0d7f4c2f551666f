"""The Markdown report and its figures, from synthetic traces of two controllers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation.metrics import compute_metrics
from fcemu.evaluation.report import ControllerResult, load_paper_tables, table_best, write_report
from fcemu.sitl.traces import Traces

pytestmark = pytest.mark.no_wall_clock

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _episodic(tau: float, name: str, n: int = 8) -> Traces:
    rng = np.random.default_rng(3)  # same seed: both controllers see the same commands
    t = np.arange(1000) * 0.001
    sp = np.repeat(rng.uniform(-5.24, 5.24, (n, 1, 3)), 1000, axis=1)
    rate = sp * (1 - np.exp(-t[None, :, None] / tau))
    pwm = 1500 + 100 * np.exp(-t[None, :, None] / tau) * np.ones((n, 1, 4))
    return Traces(t, sp, rate, pwm, controller=name, seed=3)


def _continuous(tau: float, name: str) -> Traces:
    rng = np.random.default_rng(4)
    t = np.arange(12_000) * 0.001
    holds = np.cumsum(rng.integers(100, 1000, 40))
    level_idx = np.searchsorted(holds, np.arange(t.size), side="right")
    levels = rng.uniform(-5, 5, (41, 3))
    sp = levels[level_idx][None]
    alpha = 0.001 / tau
    rate = np.zeros_like(sp)
    for k in range(1, t.size):
        rate[0, k] = rate[0, k - 1] + alpha * (sp[0, k - 1] - rate[0, k - 1])
    pwm = 1500 + 50 * (sp - rate)[..., [0, 1, 2, 0]]
    return Traces(t, sp, rate, pwm, controller=name, seed=4, task="continuous")


@pytest.fixture(scope="module")
def results() -> list[ControllerResult]:
    out = []
    for name, tau in (("pid", 0.04), ("runs/ppo|v1/policy.onnx", 0.025)):
        step = _episodic(tau, name)
        cont = _continuous(tau, name)
        out.append(ControllerResult(name, compute_metrics(step), step=step, continuous=cont))
    return out


def test_paper_tables_are_packaged() -> None:
    tables = load_paper_tables()["tables"]
    assert tables["best_vs_pid"]["PPO m=1"]["rise_ms"]["roll"] == [66.6, 3.2]
    assert tables["best_vs_pid"]["PID"]["error_rad_s"]["yaw"] == [245.1, 11.5]


def test_table_has_our_columns_and_the_papers_figures(results: list[ControllerResult]) -> None:
    table = table_best(results)
    lines = table.splitlines()
    header = lines[0]
    assert "pid" in header and r"runs/ppo\|v1/policy.onnx" in header
    assert "PPO m=1 (paper)" in header and "PID (paper)" in header
    n_cols = header.count(" | ") + 1
    assert all(line.count("|") - line.count(r"\|") == n_cols + 1 for line in lines)
    rise_roll = next(line for line in lines if line.startswith("| Rise (ms) | roll"))
    assert "66.6 ± 3.2" in rise_roll and "79.0 ± 3.5" in rise_roll
    ours = compute_metrics(results[0].step).roll.rise_ms.mean  # type: ignore[arg-type]
    assert f"{ours:.1f}" in rise_roll
    success_yaw = next(line for line in lines if line.startswith("| Success (%) | yaw"))
    assert success_yaw.endswith("100.0 ± 0.0 | 100.0 ± 0.0 |")
    paper_fail = next(line for line in lines if line.startswith("| Failure, paper's averaging (%) ² | roll"))
    assert "0.1 ± 0.1" in paper_fail
    assert "| 112.6 ± 3.0 | 136.9 ± 4.8 |" in table  # Peak roll
    assert "| 317.0 ± 11.0 | 416.1 ± 20.4 |" in table  # Error roll


def test_write_report_makes_markdown_and_pngs(tmp_path: Path, results: list[ControllerResult]) -> None:
    command = "fcemu eval --controller pid --controller policy.onnx --episodes 8 --seed 3 --report out"
    path = write_report(tmp_path / "report", results, command=command, seed=3, task="episodic")
    text = path.read_text(encoding="utf-8")
    assert command in text and "Seed 3" in text
    assert "66.6 ± 3.2" in text and "(paper)" in text
    pngs = sorted(p.name for p in path.parent.glob("*.png"))
    assert pngs == ["continuous_0_pid.png", "continuous_1_policy.onnx.png", "step_response.png"]
    for name in pngs:
        assert f"]({name})" in text
        data = (path.parent / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000


def test_step_figure_refuses_different_commands(tmp_path: Path, results: list[ControllerResult]) -> None:
    other = _episodic(0.03, "other")
    other = Traces(other.t, other.setpoint + 1.0, other.rate, other.pwm, controller="other")
    bad = [results[0], ControllerResult("other", compute_metrics(other), step=other)]
    with pytest.raises(ValueError, match="same seed"):
        write_report(tmp_path, bad, command="x", seed=0)


def test_report_without_traces_still_has_the_table(tmp_path: Path, results: list[ControllerResult]) -> None:
    bare = [ControllerResult(r.name, r.metrics) for r in results]
    path = write_report(tmp_path, bare, command="fcemu eval", seed=None)
    assert "Rise (ms)" in path.read_text(encoding="utf-8")
    assert not list(tmp_path.glob("*.png"))
