"""The Error lower bound: its constraints hold for what the twin flies, and it sits below real controllers."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from evaluation.bound import ErrorBound, error_bounds, rig_constants
from evaluation.metrics import AXES, compute_metrics
from evaluation.runner import EvalConfig, run_controller
from sim_bridge.airframe import load_airframe
from sim_bridge.tasks import episodic_commands
from sim_bridge.twin import Twin

K = 150  # a short horizon keeps each LP well under a second; the bound holds for any horizon


@pytest.fixture(scope="module")
def lp() -> ErrorBound:
    return ErrorBound(rig_constants(), K)


def fly_twin(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Held PWM (mostly full-range patterns) on the ball-joint twin for K + 1 steps.

    Returns the rotor speeds ω(k), (K + 1, 4), and every gyro frame, (K + 2, 3).
    """
    rng = np.random.default_rng(seed)
    twin = Twin(load_airframe("iris"), "rig", None, 0.001)
    frames = [twin.reset()]
    pwm = np.full(4, 1500.0)
    speeds = []
    for k in range(K + 1):
        if k % 15 == 0:
            pwm = rng.choice([1000.0, 2000.0], 4) if rng.random() < 0.7 else rng.uniform(1000, 2000, 4)
        frames.append(twin.step(pwm))
        speeds.append(twin.rotor_speed)
    return np.array(speeds), np.array([f.gyro for f in frames])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_trajectory_the_twin_flies_satisfies_the_programme(lp, seed):
    c = lp.c
    speeds, gyro = fly_twin(seed)
    # Ω(k) in the programme is the velocity after step k, which the gyro reports a step later.
    omega = gyro[2:K + 2]
    x = np.zeros(lp.n)
    for k in range(K):
        for i in range(4):
            x[lp.w(i, k)] = speeds[k, i]
            x[lp.t(i, k)] = c.kf * speeds[k, i] ** 2
        for j in range(3):
            x[lp.o(j, k)] = omega[k, j]
    rows = slice(0, lp.n_motor_rows)
    assert (lp.A_ub[rows] @ x - lp.b_ub[rows]).max() <= 1e-9 * c.kf * c.w_max**2
    lo = np.array([b[0] if b[0] is not None else -np.inf for b in lp.bounds])
    hi = np.array([b[1] if b[1] is not None else np.inf for b in lp.bounds])
    assert (x >= lo - 1e-9).all() and (x <= hi + 1e-9).all()
    # The dynamics rows hold up to the one term the bound leaves out, the gyroscopic one.
    before = np.vstack([np.zeros(3), omega[:-1]])
    gyro_acc = -np.cross(before, before * c.inertia) / c.inertia
    residual = (lp.A_eq @ x).reshape(3, K).T
    np.testing.assert_allclose(residual, c.dt * gyro_acc, atol=1e-9)
    assert np.abs(omega).max() > 0.5 and c.dt * np.abs(gyro_acc).max() > 1e3 * 1e-9  # the term is exercised


def test_zero_command_costs_nothing(lp):
    np.testing.assert_allclose(lp.solve(np.zeros(3)), 0.0, atol=1e-6)


def test_bound_sits_below_the_pid_and_grows_with_the_command(lp):
    commands = episodic_commands(7, 3)
    bounds = np.array([lp.solve(cmd) for cmd in commands])
    m = compute_metrics(run_controller("pid", EvalConfig(episodes=1, seed=7), progress=False))
    first = np.array([m.stat("error", a).mean for a in AXES])
    assert (bounds[0] < first).all()
    assert bounds[0].sum() > 0.5 * first.sum()  # and it is not vacuous
    small, large = lp.solve(np.array([1.0, 0.0, 0.0])), lp.solve(np.array([4.0, 0.0, 0.0]))
    assert 0.0 < small[0] < large[0]


def test_parallel_workers_agree_with_one_process():
    commands = episodic_commands(3, 2)
    two, one = error_bounds(commands, K, jobs=2), error_bounds(commands, K, jobs=1)
    np.testing.assert_allclose(two, one, rtol=1e-6)


def test_cli_reports_the_bound_and_each_controller_against_it():
    args = ["bound", "--episodes", "2", "--seed", "7", "--horizon", str(K), "--jobs", "1",
            "--controller", "pid"]
    run = subprocess.run([sys.executable, "-m", "fcemu", *args, "--json"],
                         capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert set(out["bound"]) == set(AXES) and out["bound_sum"] > 0
    (pid,) = out["controllers"]
    assert pid["controller"] == "pid" and pid["times_bound"] > 1.0
