"""Rate boxes: proven for every trajectory under their cap, checked against real flights of the twin."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.evaluation.bound import Floor, rig_constants
from fcemu.evaluation.open_loop import fly, horizon_error, near_optimal_pwm
from fcemu.evaluation.rate_boxes import Boxes, exit_error, gyro_coefficients, product_range
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.sim_bridge.tasks import episodic_commands

pytestmark = pytest.mark.no_wall_clock

K = 150
INDEX = 2  # seed 7's command 2, where the gyroscopic term matters most of the first five


@pytest.fixture(scope="module")
def floor() -> Floor:
    return Floor(rig_constants(), K)


def test_gyroscopic_coefficients_are_the_twins_term():
    inertia = rig_constants().inertia
    rates = np.random.default_rng(0).uniform(-6, 6, (20, 3))
    expected = -np.cross(rates, rates * inertia) / inertia
    c = gyro_coefficients(inertia)
    products = np.stack([rates[:, 1] * rates[:, 2], rates[:, 0] * rates[:, 2], rates[:, 0] * rates[:, 1]],
                        axis=1)
    np.testing.assert_allclose(c * products, expected, rtol=1e-12)


def test_product_range_holds_every_corner():
    rng = np.random.default_rng(1)
    lo = rng.uniform(-5, 1, (50, 3))
    hi = lo + rng.uniform(0, 6, (50, 3))
    c = np.array([-0.5, 0.6, -0.2])
    p_lo, p_hi = product_range(lo, hi, c)
    for _ in range(20):
        x = rng.uniform(lo, hi)
        g = c * np.stack([x[:, 1] * x[:, 2], x[:, 0] * x[:, 2], x[:, 0] * x[:, 1]], axis=1)
        assert (g >= p_lo - 1e-12).all() and (g <= p_hi + 1e-12).all()


@pytest.fixture(scope="module")
def flights() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Command 2 flown by the PID (through the firmware loop) and by the open-loop near-optimum:
    (command, rate samples over the horizon)."""
    command = episodic_commands(7, INDEX + 1)[INDEX]
    traces = run_controller("pid", EvalConfig(episodes=INDEX + 1, seed=7), progress=False)
    pwm, _ = near_optimal_pwm(rig_constants(), command, K)
    return {"pid": (command, traces.rate[INDEX, :K]), "near-optimum": (command, fly(pwm)[:K])}


@pytest.mark.parametrize("name", ["pid", "near-optimum"])
def test_boxes_hold_a_real_flight_under_their_cap(floor, flights, name):
    command, rates = flights[name]
    cap = horizon_error(command, rates)  # the flight is under (at) the cap, so it must stay inside
    omega = rates[2:]  # sample k + 2 is Ω(k)
    crude = floor.boxes.crude(command, cap)
    assert crude is not None and crude.contains(omega, tol=1e-9)
    others = np.zeros(3)
    for j in range(3):
        sol = floor.short.solve(command, crude[:floor.short.K], tuple(float(i != j) for i in range(3)))
        others[j] = sol.error.sum() - sol.error[j]
    tight = floor.boxes.refine(command, cap, crude, others)
    assert tight.contains(omega, tol=1e-9)
    # The refinement does something: its boxes are narrower than the crude ones.
    assert (tight.hi - tight.lo).sum() < 0.9 * (crude.hi - crude.lo).sum()


def test_a_start_a_trajectory_under_the_cap_can_leave_is_not_taken(floor):
    command = episodic_commands(7, INDEX + 1)[INDEX]
    cap = floor.lp.solve(command).error.sum()
    rb = floor.boxes
    forced = rb.forced_error(command, rb.reach)
    narrow = Boxes(np.maximum(rb.reach.lo, -1.0), np.minimum(rb.reach.hi, 1.0))  # the command is ±3…5 rad/s
    assert rb._certify(command, cap, narrow, forced.sum() - forced, rb.reach, rb.reach_accel) is None
    assert rb.crude(command, cap) is not None


@pytest.mark.parametrize(("axis", "step", "rate", "side"), [(0, 60, 0.0, 1), (2, 100, 0.3, -1)])
def test_exit_error_is_below_what_a_flight_through_that_rate_scores(floor, axis, step, rate, side):
    """A planned flight forced past `rate` at `step` (roll back up to 0 at 60 ms against a −5.2
    command; yaw held under 0.3 at 100 ms against +3.1): the axis's Error it flies is at least
    `exit_error`'s, computed over the reachable boxes that hold every flight, and not far above."""
    c, rb = floor.lp.c, floor.boxes
    command = episodic_commands(7, INDEX + 1)[INDEX]
    pwm, _ = near_optimal_pwm(c, command, K, through=(axis, step, rate, side))
    rates = fly(pwm)
    flown = np.abs(command[axis] - rates[:, axis]).sum()
    v = np.full(K, side * rates[step + 2, axis])  # sample k + 2 is Ω(k)
    reach, (a_lo, a_hi) = rb.reach, rb.reach_accel
    lo, hi, up, down = reach.lo[:, axis], reach.hi[:, axis], a_hi[:, axis] * c.dt, a_lo[:, axis] * c.dt
    if side > 0:
        cost = exit_error(command[axis], lo, hi, up, lo, hi, down, rb.n_err)
    else:
        cost = exit_error(-command[axis], -hi, -lo, -down, -hi, -lo, -up, rb.n_err)
    least = cost(v)[step]
    assert least <= flown
    assert least > 0.5 * flown
