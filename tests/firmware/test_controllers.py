"""`default`: the shipped policy where it holds the airframe, else the airframe's PID (on a long
loop, its tune for latency)."""

from dataclasses import replace

import numpy as np
import pytest

from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.controllers import (
    DEFAULT,
    DEFAULT_POLICY,
    DEFAULT_POLICY_LONGEST_LOOP_TICKS,
    default_for,
    load_controller,
    resolve,
)
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sitl.sitl import flying_line

IRIS = airframe_spec("iris")


def test_the_default_is_the_shipped_policy_on_the_loops_it_holds():
    assert IRIS.loop_delay_ticks == 0 and airframe_spec("iris_realistic").loop_delay_ticks == 3
    for ticks in range(DEFAULT_POLICY_LONGEST_LOOP_TICKS + 1):
        assert default_for(replace(IRIS, loop_delay_ticks=ticks)) == str(DEFAULT_POLICY)
    assert resolve("pid", IRIS) == "pid" and resolve(DEFAULT, None) == str(DEFAULT_POLICY)


def test_on_a_longer_loop_the_default_is_the_pid_tuned_for_latency_and_says_why():
    long_loop = replace(IRIS, loop_delay_ticks=DEFAULT_POLICY_LONGEST_LOOP_TICKS + 1)
    assert default_for(long_loop) == "pid:iris_robust"
    robust = load_controller(DEFAULT, airframe=long_loop)
    tuned = load_controller("pid", airframe=IRIS)
    assert robust.gains.kp[0] == pytest.approx(tuned.gains.kp[0] * 0.7, rel=1e-4)
    assert "pid:iris_robust (the default for iris, on a loop of 4 ticks" in flying_line(DEFAULT, long_loop)
    assert flying_line(DEFAULT, IRIS).startswith("fcemu: flying neural:iris_rate_ppo")


def test_where_the_shipped_policy_refuses_the_airframe_the_default_is_its_tune():
    x500 = airframe_spec("x500")
    assert default_for(x500) == "pid" == default_for(replace(x500, loop_delay_ticks=5))  # no latency tune
    line = flying_line(DEFAULT, x500)
    assert "the shipped policy refuses it: policy iris_rate_ppo.onnx was made for iris" in line


def test_eval_flies_the_default_each_airframe_resolves_to():
    """One command flies the policy on a short loop and the latency tune on a long one."""
    cfg = EvalConfig(episodes=2, seed=3)
    long_loop = load_airframe("iris").scaled(esc_delay_ticks=2, gyro_delay_ticks=3)
    for airframe, expected in ((None, str(DEFAULT_POLICY)), (long_loop, "pid:iris_robust")):
        flown = run_controller(DEFAULT, cfg, progress=False, airframe=airframe)
        named = run_controller(expected, cfg, progress=False, airframe=airframe)
        np.testing.assert_array_equal(flown.pwm, named.pwm)
