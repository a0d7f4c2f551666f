"""CAPS: the smoothness terms themselves, and a short training run with them on the realistic airframe."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy

from fcemu.training.caps import consecutive_pairs, spatial_smoothness, temporal_smoothness
from fcemu.training.regularised_ppo import RegularisedPPO
from fcemu.training.train import TrainConfig, train

pytestmark = pytest.mark.no_wall_clock

OBS = spaces.Box(-np.inf, np.inf, (7,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (4,), np.float32)


def toy_policy(seed: int = 0) -> ActorCriticPolicy:
    th.manual_seed(seed)
    return ActorCriticPolicy(OBS, ACT, lambda _: 1e-3, net_arch=[32, 32], use_sde=True, log_std_init=-1.0)


def toy_batch(seed: int = 1) -> tuple[th.Tensor, th.Tensor]:
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(256, 7)).astype(np.float32)
    nxt = obs + 0.3 * rng.normal(size=obs.shape).astype(np.float32)
    return th.as_tensor(obs), th.as_tensor(nxt)


def test_terms_are_zero_for_a_constant_policy():
    policy = toy_policy()
    with th.no_grad():  # a policy that ignores its input: last actor layer weights 0
        policy.action_net.weight.zero_()
        policy.action_net.bias.fill_(0.3)
    obs, nxt = toy_batch()
    gen = th.Generator().manual_seed(0)
    assert temporal_smoothness(policy, obs, nxt).item() == 0.0
    assert spatial_smoothness(policy, obs, 0.5, gen).item() == 0.0


def test_terms_are_positive_and_fall_under_their_own_gradient():
    policy = toy_policy()
    obs, nxt = toy_batch()
    gen = th.Generator().manual_seed(0)
    optimizer = th.optim.Adam(policy.parameters(), lr=3e-3)
    start_t = temporal_smoothness(policy, obs, nxt).item()
    start_s = spatial_smoothness(policy, obs, 0.3, gen).item()
    assert start_t > 0.0 and start_s > 0.0
    for _ in range(30):
        optimizer.zero_grad()
        (temporal_smoothness(policy, obs, nxt) + spatial_smoothness(policy, obs, 0.3, gen)).backward()
        optimizer.step()
    end_t = temporal_smoothness(policy, obs, nxt).item()
    end_s = spatial_smoothness(policy, obs, 0.3, gen).item()
    assert end_t < 0.5 * start_t and end_s < 0.5 * start_s


def test_pairs_never_cross_an_episode_boundary():
    obs = np.arange(5 * 2, dtype=np.float32).reshape(5, 2, 1)  # steps × envs
    starts = np.zeros((5, 2), dtype=np.float32)
    starts[3, 0] = 1.0  # env 0 starts a new episode at step 3
    s, s_next = consecutive_pairs(obs, starts)
    pairs = {(float(a), float(b)) for a, b in zip(s[:, 0], s_next[:, 0], strict=True)}
    assert (4.0, 6.0) not in pairs  # env 0: step 2 → 3 crosses the boundary
    assert pairs == {(0.0, 2.0), (2.0, 4.0), (6.0, 8.0), (1.0, 3.0), (3.0, 5.0), (5.0, 7.0), (7.0, 9.0)}


def test_a_rollout_without_pairs_trains_as_plain_ppo():
    from stable_baselines3.common.env_util import make_vec_env

    model = RegularisedPPO("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), n_steps=1,
                           batch_size=2, n_epochs=1, seed=0, device="cpu", caps_temporal=1.0,
                           caps_spatial=1.0)
    model.learn(4)  # one step per environment: no (s_t, s_t+1) pair in any rollout
    assert model.num_timesteps == 4


def test_weights_must_be_non_negative():
    with pytest.raises(ValueError, match="caps_temporal"):
        RegularisedPPO("MlpPolicy", "Pendulum-v1", caps_temporal=-1.0)
    with pytest.raises(ValueError, match="for PPO"):
        TrainConfig(algo="sac", caps_spatial=0.1)


@pytest.mark.slow
def test_a_short_run_with_caps_on_the_realistic_airframe_trains_end_to_end(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "caps"
    cfg = TrainConfig(steps=2048, seed=2, out=str(out), envs=8, eval_episodes=0, progress=False,
                      airframe="iris_realistic", caps_temporal=0.1, caps_spatial=0.5, caps_sigma=0.1,
                      action_rate_penalty=0.1, hp={"n_steps": 128, "batch_size": 256, "n_epochs": 2})
    summary = train(cfg)
    assert summary["steps"] == 2048 and summary["export"]["parity_ok"]
    config = json.loads((out / "config.json").read_text())
    assert config["caps"] == {"temporal": 0.1, "spatial": 0.5, "sigma": 0.1}
    assert config["env"]["airframe"] == "iris_realistic"
    acc = EventAccumulator(str(next((out / "tb").iterdir())))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    assert {"train/caps_temporal", "train/caps_spatial", "reward/action_rate"} <= set(tags)
    assert all(e.value > 0.0 for e in acc.Scalars("train/caps_spatial"))


def _learned(algo: type, **caps: float) -> list[th.Tensor]:
    model = algo("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=32, n_epochs=2, seed=5, device="cpu",
                 policy_kwargs={"net_arch": [16, 16]}, **caps)
    model.learn(128)
    assert "zero_grad" not in vars(model.policy.optimizer)  # the hook is gone after train()
    return [p.detach().clone() for p in model.policy.parameters()]


@pytest.mark.slow
def test_caps_enters_the_ppo_update_and_nothing_else_changes():
    from stable_baselines3 import PPO

    plain = _learned(PPO)
    zero = _learned(RegularisedPPO, caps_temporal=0.0, caps_spatial=0.0)
    caps = _learned(RegularisedPPO, caps_temporal=1.0, caps_spatial=1.0, caps_sigma=0.2)
    assert all(th.equal(a, b) for a, b in zip(plain, zero, strict=True))  # λ = 0: PPO to the bit
    assert any(not th.equal(a, b) for a, b in zip(plain, caps, strict=True))


def test_the_anchor_pulls_the_policy_towards_the_teachers_actions():
    from stable_baselines3.common.env_util import make_vec_env

    def fitted(anchor: float) -> float:
        model = RegularisedPPO("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), n_steps=64,
                               batch_size=32, n_epochs=4, seed=3, device="cpu", anchor=anchor,
                               learning_rate=3e-3, policy_kwargs={"net_arch": [16, 16]})
        rng = np.random.default_rng(0)
        obs = rng.uniform(-1.0, 1.0, (256, 3)).astype(np.float32)
        labels = np.full((256, 1), 1.5, dtype=np.float32)  # a teacher that always pushes +1.5
        model.set_anchor_data(obs, labels, lambda raw: raw)
        model.learn(1024)
        with th.no_grad():
            act = model.policy.get_distribution(th.as_tensor(obs)).mode().numpy()
        return float(np.mean((act - labels) ** 2))

    assert fitted(50.0) < 0.25 * fitted(0.0)  # PPO alone never learns the teacher's constant


def test_anchor_data_must_match_the_action_space_and_the_option_needs_a_warm_start():
    model = RegularisedPPO("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=32, device="cpu", anchor=1.0)
    with pytest.raises(ValueError, match="anchor data"):
        model.set_anchor_data(np.zeros((4, 3)), np.zeros((4, 2)), lambda raw: raw)
    with pytest.raises(ValueError, match="anchor must be finite"):
        RegularisedPPO("MlpPolicy", "Pendulum-v1", anchor=-1.0)
    with pytest.raises(ValueError, match="needs --algo ppo and --warm-start or --init"):
        TrainConfig(anchor=0.5)
    with pytest.raises(ValueError, match="finite and >= 0"):
        TrainConfig(anchor=-0.5, warm_start="pid")
    assert TrainConfig(anchor=0.5, warm_start="pid").anchor == 0.5


def test_a_checkpoint_leaves_the_anchor_data_out(tmp_path):
    model = RegularisedPPO("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=32, device="cpu", anchor=1.0)
    model.set_anchor_data(np.zeros((200_000, 3), dtype=np.float32), np.zeros((200_000, 1), dtype=np.float32),
                          lambda raw: raw)
    model.save(tmp_path / "m.zip")
    assert (tmp_path / "m.zip").stat().st_size < 1_000_000  # the data alone are 3.2 MB
    assert RegularisedPPO.load(tmp_path / "m.zip", device="cpu")._anchor_data is None
