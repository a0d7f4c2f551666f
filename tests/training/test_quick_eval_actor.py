"""The in-training evaluator's actor: the deterministic action SB3's `predict` gives, faster."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import VecNormalize

from fcemu.training import quick_eval
from fcemu.training.train import TrainConfig, make_model, make_vec_env


@pytest.mark.parametrize("squash", [False, True])
def test_actor_gives_predicts_actions_bit_for_bit(tmp_path: Path, squash: bool):
    cfg = TrainConfig(envs=8, seed=4, squash=squash, out=str(tmp_path), progress=False)
    venv = VecNormalize(make_vec_env(cfg), gamma=0.99)
    model = make_model(cfg, venv, tmp_path / "tb")
    with torch.no_grad():  # mean actions well beyond ±1, so the clip or the squash matters
        model.policy.action_net.weight.mul_(300.0)
    venv.reset()
    rng = np.random.default_rng(0)
    for _ in range(50):  # observations of a flight, and VecNormalize's statistics moving
        venv.step(rng.uniform(-1, 1, (8, 4)).astype(np.float32))
    raw = venv.get_original_obs()
    act = quick_eval.sb3_actor(model, venv)
    expected = model.predict(venv.normalize_obs(raw), deterministic=True)[0]
    got = act(raw)
    assert got.dtype == expected.dtype and got.shape == (8, 4)
    np.testing.assert_array_equal(got, expected)
    assert np.abs(got).max() > 0.99  # saturated actions were part of the comparison
    venv.close()
