"""The bound's programme kept between solves: warm starts and lazy rows give the whole programme's
optimum, as a fresh solve of every row by scipy's HiGHS does."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linprog

from fcemu.evaluation.bound import ErrorBound, rig_constants
from fcemu.evaluation.rate_boxes import RateBoxes
from fcemu.sim_bridge.tasks import episodic_commands

pytestmark = pytest.mark.no_wall_clock

K = 60


def whole_programme(lp: ErrorBound, command: np.ndarray) -> float:
    """The gyroscope-free optimum with every row, tangents and all, solved from scratch."""
    b_ub = lp.b_ub.copy()
    pairs = b_ub[lp.slack_rows].reshape(3, K - 2, 2)
    pairs[..., 0], pairs[..., 1] = -command[:, None], command[:, None]
    cost = np.zeros(lp.n)
    for j in range(3):
        cost[lp.s(j, 2):lp.s(j, K - 1) + 1] = 1.0
        cost[lp.off_tail + j] = 1.0
    res = linprog(cost, A_ub=lp.A_ub, b_ub=b_ub, A_eq=lp.A_eq, b_eq=lp.b_eq, bounds=lp.bounds, method="highs")
    assert res.status == 0
    return float(res.fun + 2.0 * np.abs(command).sum())


def test_warm_solves_with_lazy_tangents_reach_the_whole_programmes_optimum():
    lp = ErrorBound(rig_constants(), K, episode=None)
    for command in episodic_commands(11, 4):
        assert lp.solve(command).error.sum() == pytest.approx(whole_programme(lp, command), rel=1e-7)
    programme = lp.programme()
    assert 0 < programme.added.sum() < 0.5 * lp.tangent_rows.sum()  # the lazy rows did their work


def test_a_box_solve_and_the_free_solve_after_it_are_each_a_fresh_models():
    c = rig_constants()
    warm = ErrorBound(c, K, episode=None)
    command = episodic_commands(11, 1)[0]
    box = RateBoxes(c, K).reach
    first = warm.solve(command, box)
    again = warm.solve(command)  # the box's rows are gone
    fresh_box = ErrorBound(c, K, episode=None).solve(command, box)
    assert first.error.sum() == pytest.approx(fresh_box.error.sum(), rel=1e-7)
    assert again.error.sum() == pytest.approx(whole_programme(warm, command), rel=1e-7)
