"""The reward lives in the env: weights as arguments, terms in info, the training reward reproduced."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.reward import REWARD_TERMS, RateReward
from fcemu.sim_bridge.vec_env import BatchedRateEnv

# The float32 rewards of training's former SB3 wrapper (RewardOption, VecEnvWrapper over the batched
# env) for BatchedRateEnv(3, **env) reset with seed=4 and the actions of `_actions`, recorded from it before
# the reward moved into the env: rewards at steps 0, 1, 99, 100 (first of the second episode), 399,
# and each copy's sum over the 400 steps.
CASES = {
    "unclipped-weights": (
        dict(action_mapping="throttle", throttle=(0.5, 0.9), action_rate_penalty=0.5, episode_s=0.1,
             reward="unclipped", axis_weights=(1.0, 2.0, 3.0)),
        {0: [-1.262961506843567, -0.6445741057395935, -0.49628058075904846],
         1: [-1.406076192855835, -0.7047473788261414, -0.7003785371780396],
         99: [-1.8502249717712402, -1.4172767400741577, -0.8214980959892273],
         100: [-0.8400575518608093, -0.6359412670135498, -0.8506195545196533],
         399: [-2.0743839740753174, -2.1373157501220703, -2.2272300720214844]},
        [-566.7538425326347, -510.5244276225567, -507.77156832814217]),
    "unclipped-continuous": (
        dict(action_mapping="throttle", throttle=(0.5, 0.9), action_rate_penalty=2.0, episode_s=0.1,
             task="continuous", reward="unclipped"),
        {0: [-0.0, -0.0, -0.0],
         1: [-0.5723479390144348, -0.24076195061206818, -0.8161189556121826],
         99: [-0.6508347988128662, -1.4255753755569458, -0.703926146030426],
         100: [-0.0, -0.0, -0.0],
         399: [-0.3791181147098541, -0.3714487552642822, -0.3922377824783325]},
        [-174.53042242609808, -172.05134498168627, -188.943491057762]),
    "paper": (
        dict(action_mapping="gymfc", action_rate_penalty=0.1, episode_s=0.1),
        {0: [-0.6204182505607605, -0.4188461899757385, -0.21721749007701874],
         1: [-0.6573907732963562, -0.437141090631485, -0.2580695152282715],
         99: [-0.8905837535858154, -0.7108172178268433, -0.37022578716278076],
         100: [-0.4333554804325104, -0.5179327130317688, -0.49713632464408875],
         399: [-0.6698552370071411, -0.9767668843269348, -0.4537881016731262]},
        [-231.2426260113716, -218.47093792259693, -190.5832996815443]),
}
STEPS = 400


def _actions(steps: int, n: int) -> list[np.ndarray]:
    """Random actions for 40 steps, full differential (spinning up) for 40, and so on."""
    rng = np.random.default_rng(5)
    spin = np.tile(np.float32([1, -1, 1, -1]), (n, 1))
    return [rng.uniform(-1, 1, (n, 4)).astype(np.float32) if k % 80 < 40 else spin for k in range(steps)]


@pytest.mark.parametrize("name", CASES)
def test_env_reward_is_the_former_training_wrapper_to_the_bit(name):
    env_kwargs, picked, sums = CASES[name]
    venv = BatchedRateEnv(3, **env_kwargs)
    venv.reset(seed=4)
    rewards = np.array([venv.step(a)[1].astype(np.float32) for a in _actions(STEPS, 3)])
    venv.close()
    assert rewards.dtype == np.float32
    for k, expected in picked.items():
        np.testing.assert_array_equal(rewards[k], np.float32(expected), err_msg=f"step {k}")
    np.testing.assert_array_equal(rewards.astype(np.float64).sum(axis=0), sums)


def test_terms_add_up_and_the_single_env_is_the_batch():
    kw = dict(action_mapping="throttle", throttle=(0.5, 0.9), action_rate_penalty=0.7, episode_s=0.05,
              reward="unclipped", axis_weights=(0.5, 1.0, 2.0))
    batch = BatchedRateEnv(2, **kw)
    singles = [RateControlEnv(**kw) for _ in range(2)]
    batch.reset(seed=1)
    for i, env in enumerate(singles):
        env.reset(seed=1 + i)
    for k, actions in enumerate(_actions(120, 2)):
        _, reward, _, truncated, info = batch.step(actions)
        np.testing.assert_array_equal(reward, info["reward_tracking"] + info["reward_action_rate"])
        np.testing.assert_array_equal(info["reward_action_rate"], -0.7 * info["action_rate"])
        for i, env in enumerate(singles):
            _, r, _, trunc, inf = env.step(actions[i])
            assert r == reward[i] and isinstance(r, float)
            for key in REWARD_TERMS:
                assert inf[key] == info[key][i] and isinstance(inf[key], float), (key, k, i)
            if trunc:
                env.reset()
        assert truncated.any() == (k % 50 == 49)


def test_weights_change_only_what_they_weight():
    env = RateControlEnv(reward="unclipped", axis_weights=(1.0, 1.0, 3.0))
    env.reset(seed=2)
    _, reward, _, _, info = env.step(np.zeros(4, dtype=np.float32))
    e = np.abs(info["setpoint"] - info["rate"])
    assert reward == pytest.approx(-(e[0] + e[1] + 3 * e[2]) / (3 * 5.24), rel=1e-12)
    assert info["paper_reward"] == pytest.approx(-e.sum() / (3 * 5.24), rel=1e-12)  # reported unweighted


def test_gymnasium_checker_passes_with_non_default_weights():
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*infinity.*")  # the paper's observations are unbounded
        check_env(RateControlEnv(reward="unclipped", axis_weights=(1.0, 2.0, 0.5), action_rate_penalty=2.0,
                                 action_mapping="throttle", throttle=(0.5, 0.9), episode_s=0.2),
                  skip_render_check=True)
        env = gym.make("fcemu/RateEpisodic-v0", reward="unclipped", axis_weights=[1.0, 2.0, 3.0],
                       action_rate_penalty=0.5)
        assert env.unwrapped.config.rate_reward == RateReward("unclipped", (1.0, 2.0, 3.0), 0.5)
        env.reset(seed=0)
        assert set(REWARD_TERMS) <= set(env.step(env.action_space.sample())[4])


@pytest.mark.parametrize(("kwargs", "match"), [
    (dict(reward="shaped"), "unknown reward"),
    (dict(axis_weights=(1.0, 1.0, 2.0)), "unclipped"),
    (dict(reward="unclipped", axis_weights=(1.0, 2.0)), "3 finite weights"),
    (dict(reward="unclipped", axis_weights=(1.0, -1.0, 1.0)), "3 finite weights"),
    (dict(action_rate_penalty=-0.1), "action_rate_penalty"),
    (dict(action_rate_penalty=float("nan")), "action_rate_penalty"),
    (dict(relative_error=0.1), "unclipped reward"),
    (dict(reward="unclipped", relative_error=-1.0), "relative_error"),
])
def test_bad_weights_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RateControlEnv(**kwargs)
    with pytest.raises(ValueError, match=match):
        BatchedRateEnv(2, **kwargs)


@pytest.mark.parametrize("task", ["episodic", "continuous"])
def test_a_gated_penalty_waits_for_the_setpoint_to_be_held(task):
    after_s, dt, steps = 0.03, 0.001, 2000
    env = RateControlEnv(task=task, reward="unclipped", action_rate_penalty=1.0, action_rate_after_s=after_s,
                         episode_s=steps * dt)
    env.reset(seed=4)
    rng = np.random.default_rng(0)
    held, previous, changes, penalised_steps, charged = 0, None, 0, 0, 0.0
    for _ in range(steps):
        _, _, _, _, info = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        # both tasks begin held (episodic: one setpoint; continuous: a rest), so the first step counts 1
        changed = previous is not None and not np.array_equal(info["setpoint"], previous)
        held, changes = (0, changes + 1) if changed else (held + 1, changes)
        previous = info["setpoint"].copy()
        penalised = held >= round(after_s / dt)
        penalised_steps += penalised
        assert info["reward_action_rate"] == pytest.approx(-info["action_rate"] if penalised else 0.0)
        charged += -info["reward_action_rate"]
    assert changes >= (2 if task == "continuous" else 0) and 0 < penalised_steps < steps and charged > 0


def test_the_gate_is_checked():
    with pytest.raises(ValueError, match="action_rate_after_s"):
        RateControlEnv(action_rate_after_s=-0.1)


def test_the_relative_error_weighs_each_axis_error_by_its_commands_step():
    """On the continuous task, with the command changing mid-episode: −K·Σ|e|/(|e0| + 0.1)/3 on top of
    the unclipped term, |e0| each axis's error on the step its command began; the batch gives the same."""
    kw = dict(task="continuous", reward="unclipped", relative_error=0.2, episode_s=2.0)
    env, plain = RateControlEnv(**kw), RateControlEnv(**{**kw, "relative_error": 0.0})
    batch = BatchedRateEnv(1, **kw)
    env.reset(seed=6), plain.reset(seed=6), batch.reset(seed=6)
    command, e0, changes = None, None, 0
    for action in _actions(2000, 1):
        _, reward, _, _, info = env.step(action[0])
        base = plain.step(action[0])[1]
        e = np.abs(info["setpoint"] - info["rate"])
        if command is None or not np.array_equal(info["setpoint"], command):
            command, e0, changes = info["setpoint"].copy(), e, changes + 1
        assert reward == pytest.approx(base - 0.2 * (e / (e0 + 0.1)).sum() / 3, rel=1e-9, abs=1e-12)
        assert batch.step(action)[1][0] == reward
    assert changes >= 3
