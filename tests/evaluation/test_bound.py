"""The Error lower bound: its rows hold for what the twin flies, and nothing flown goes below it."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from fcemu.evaluation.bound import ErrorBound, Floor, error_bounds, rig_constants, tail_axes
from fcemu.evaluation.open_loop import near_optimal_pwm
from fcemu.evaluation.rate_boxes import RateBoxes
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.errors import UserError
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.tasks import episodic_commands
from fcemu.sim_bridge.twin import Twin

pytestmark = pytest.mark.no_wall_clock

K = 150  # a short horizon keeps each programme well under a second; the bound holds for any horizon


@pytest.fixture(scope="module")
def floor() -> Floor:
    return Floor(rig_constants(), K)


def fly_twin(seed: int, airframe: str = "iris", steps: int = K) -> tuple[np.ndarray, np.ndarray]:
    """Held PWM (mostly full-range patterns) on the ball-joint twin for `steps` + 1 steps.

    Returns the rotor speeds ω(k), (steps + 1, 4), and every gyro frame, (steps + 2, 3).
    """
    rng = np.random.default_rng(seed)
    twin = Twin(load_airframe(airframe), "rig", None, 0.001)
    frames = [twin.reset()]
    pwm = np.full(4, 1500.0)
    speeds = []
    for k in range(steps + 1):
        if k % 15 == 0:
            pwm = rng.choice([1000.0, 2000.0], 4) if rng.random() < 0.7 else rng.uniform(1000, 2000, 4)
        frames.append(twin.step(pwm))
        speeds.append(twin.rotor_speed)
    return np.array(speeds), np.array([f.gyro for f in frames])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_trajectory_the_twin_flies_satisfies_the_programme(floor, seed):
    lp, c = floor.lp, floor.lp.c
    speeds, gyro = fly_twin(seed)
    # Ω(k) in the programme is the velocity after step k, which the gyro reports two frames on.
    omega = gyro[2:K + 2]
    products = lp.gyro_of(omega)
    x = np.zeros(lp.n)
    for k in range(K):
        for i in range(4):
            x[lp.w(i, k)] = speeds[k, i]
            x[lp.t(i, k)] = c.kf * speeds[k, i] ** 2
        for j in range(3):
            x[lp.o(j, k)] = omega[k, j]
            x[lp.g(j, k)] = products[k, j]
    rows = slice(0, lp.n_motor_rows)
    assert (lp.A_ub[rows] @ x - lp.b_ub[rows]).max() <= 1e-9 * c.kf * c.w_max**2
    # The dynamics rows, gyroscopic term and all, are the twin's step to rounding.
    np.testing.assert_allclose(lp.A_eq @ x, 0.0, atol=1e-12)
    assert np.abs(omega).max() > 0.5 and np.abs(products).max() > 0.2  # the term is exercised
    # Every flight stays in the reachable boxes, and McCormick's rows over them hold.
    boxes = RateBoxes(c, K).reach
    assert boxes.contains(omega)
    rows, rhs = lp.mccormick(boxes)
    assert (rows @ x - rhs).max() <= 1e-9


@pytest.mark.parametrize("seed", [0, 1])
def test_the_tail_holds_for_what_the_twin_flies_on_a_symmetric_frame(seed):
    """On the X500 (equal roll and pitch moments) yaw has no gyroscopic term, so its bound runs on
    to the episode's end: each tail row holds with the flight's own error after the horizon."""
    c, episode = rig_constants("x500"), 400
    lp = ErrorBound(c, K, episode)
    assert lp.tail_axes == (2,) and tail_axes(rig_constants("iris"), K, episode) == ()
    _, gyro = fly_twin(seed, "x500", episode)
    rate = gyro[:episode]  # the evaluation's sample k is gyro frame k: Ω(k − 2)
    command = np.array([0.0, 0.0, 4.0])
    x = np.zeros(lp.n)
    x[lp.s(2, K - 1)] = abs(command[2] - rate[K - 1, 2])
    x[lp.off_tail + 2] = np.abs(command[2] - rate[K:, 2]).sum()
    rows = slice(lp.slack_rows.stop, None)
    assert lp.A_ub[rows].shape[0] == episode - K
    assert (lp.A_ub[rows] @ x - lp.b_ub[rows]).max() <= 1e-9
    tail_floor = (lp.A_ub[rows] @ x - lp.b_ub[rows]).max() + x[lp.off_tail + 2]  # the most any cut asks
    assert 0.0 < tail_floor <= x[lp.off_tail + 2]


def test_on_a_symmetric_frame_a_slow_yaw_costs_its_whole_episode_and_no_flight_goes_below(tmp_path):
    """Seed 2019's command 5 asks the X500 for 4.9 rad/s of yaw, more than 0.4 s of its yaw authority
    gives: the tail raises the bound, and a PID flown on it is still above it on the samples covered."""
    c = rig_constants("x500")
    command = episodic_commands(2019, 6)[5]
    with_tail = Floor(c, K).solve(command).bound
    horizon_only = ErrorBound(c, K, episode=None).solve(command).error.sum()
    assert with_tail > 1.5 * horizon_only
    traces = run_controller("pid:iris", EvalConfig(episodes=6, seed=2019, airframe="x500"), progress=False)
    error = np.abs(traces.setpoint[5] - traces.rate[5])
    error[K:, :2] = 0.0  # roll and pitch: the horizon's samples only
    assert error.sum() >= with_tail


def test_zero_command_costs_nothing(floor):
    assert floor.solve(np.zeros(3)).bound == pytest.approx(0.0, abs=1e-6)


def test_the_free_programme_grows_with_the_command(floor):
    small, large = floor.lp.solve(np.array([1.0, 0.0, 0.0])), floor.lp.solve(np.array([4.0, 0.0, 0.0]))
    assert 0.0 < small.error[0] < large.error[0]


@pytest.mark.parametrize("index", [2, 62])
def test_a_near_optimal_flight_goes_below_the_gyroscope_free_programme_but_not_below_the_bound(floor, index):
    """Commands 2 and 62 of seed 7: the twin's gyroscopic term helps them, so a flight planned
    with it beats the programme that leaves it out; the bound, which carries it, still holds."""
    command = episodic_commands(7, index + 1)[index]
    found = floor.solve(command)
    _, flown = near_optimal_pwm(floor.lp.c, command, K)
    assert flown < 0.995 * found.without_gyro
    assert found.bound <= flown
    assert found.bound > 0.95 * flown  # and it is not vacuous


def test_parallel_workers_agree_with_one_process():
    commands = episodic_commands(3, 2)
    two, one = error_bounds(commands, 60, jobs=2), error_bounds(commands, 60, jobs=1)
    np.testing.assert_allclose([b.bound for b in two], [b.bound for b in one], rtol=1e-6)


def test_cli_flies_pid_and_the_policy_against_the_bound_and_neither_goes_below():
    args = ["bound", "--episodes", "3", "--seed", "7", "--horizon", str(K), "--jobs", "1",
            "--controller", "pid", "--controller", "policies/iris_rate_ppo.onnx"]
    run = subprocess.run([sys.executable, "-m", "fcemu", *args, "--json"],
                         capture_output=True, text=True, timeout=600, check=False)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert "bound" not in out and set(out["split_at_optimum"]) == {"roll", "pitch", "yaw"}
    assert out["tail_axes"] == []  # the Iris has a gyroscopic term on every axis
    assert 0 < out["bound_sum"] <= out["without_gyro_sum"]
    assert sum(out["split_at_optimum"].values()) == pytest.approx(out["bound_sum"], abs=0.05)
    for flown in out["controllers"]:
        assert flown["below_bound"] == 0 and flown["times_bound"] > 1.0, flown


def test_an_airframe_with_effects_on_and_bad_arguments_are_refused():
    with pytest.raises(UserError, match=r"nominal twin only.*rate damping"):
        rig_constants("iris_realistic")
    for args, message in ((["--airframe", "iris_realistic"], "the bound models the nominal twin only"),
                          (["--horizon", "2"], "bound: --episodes must be")):
        run = subprocess.run([sys.executable, "-m", "fcemu", "bound", *args],
                             capture_output=True, text=True, timeout=120, check=False)
        assert run.returncode == 2 and not run.stdout
        assert run.stderr.startswith(f"fcemu: error: {message}") and len(run.stderr.strip().splitlines()) == 1
