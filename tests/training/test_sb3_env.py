"""The SB3 adapter over the batched twins: SB3's VecEnv API, and PPO learns through it."""

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from fcemu.sim_bridge.env import RateControlEnv
from fcemu.training.sb3_env import SB3VecEnv, make_sb3_vec_env


def test_sb3_adapter_api():
    venv = make_sb3_vec_env(3, seed=5, episode_s=0.01)
    assert isinstance(venv, VecEnv) and isinstance(venv, SB3VecEnv) and venv.num_envs == 3
    obs = venv.reset()
    assert obs.shape == (3, 7) and obs.dtype == np.float32
    np.testing.assert_array_equal(obs[2], RateControlEnv(episode_s=0.01).reset(seed=7)[0])
    for k in range(1, 11):
        obs, rewards, dones, infos = venv.step(np.zeros((3, 4), dtype=np.float32))
        assert rewards.shape == (3,) and rewards.dtype == np.float32 and len(infos) == 3
        assert dones.all() == (k == 10)
    for info in infos:
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"].shape == (7,)
    assert not np.array_equal(infos[0]["terminal_observation"], obs[0])
    assert venv.get_attr("num_envs", [0, 1]) == [3, 3]
    results = venv.env_method("reset", seed=1, indices=[0, 2])
    assert len(results) == 2 and results[0][0].shape == (3, 7)
    assert venv.env_is_wrapped(object) == [False, False, False]
    venv.set_attr("render_mode", None)
    venv.close()


def test_ppo_learns_on_the_adapter():
    venv = VecMonitor(make_sb3_vec_env(8, seed=0, episode_s=0.05))
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=256, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=2048)
    assert model.num_timesteps >= 2048
    assert len(model.ep_info_buffer) >= 8  # episodes ended, were reset and reported
    assert all(ep["l"] == 50 for ep in model.ep_info_buffer)
    venv.close()
