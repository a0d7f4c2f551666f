"""Warm start: a PID teaches the network before reinforcement learning takes over.

PPO from a random network spends most of its steps learning to fly at all. Here the
tuned PID (a firmware preset, `PIDRateController`) flies the training environments; its
motor outputs, turned into the policy's action (`firmware.action.pwm_to_action`, the
inverse of the action mapping), are the labels. The actor's mean is fitted to them (behaviour
cloning, with DAgger rounds: later rounds fly the network and the PID labels the states
the network visits), and the critic to the discounted returns of those flights, so PPO's
first advantages are not noise. The PID sees what the policy sees: the setpoint and the
measured gyro (decoded from the observation's rate error), with noise, delay and the
episode's randomised airframe.

The environment steps spent here are reported (`env_steps` in what `run` returns); they are not in
the algorithm's step count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fcemu.training import quick_eval
from fcemu.training.config import WARM_START_ROUNDS, WARM_START_STEPS
from fcemu.training.warm_start_teacher import PidTeacher, episode_delay_ticks, teacher_inputs


@dataclass
class WarmStart:
    rounds: int = WARM_START_ROUNDS  # the first flies the PID, the others the network (DAgger)
    steps_per_round: int = WARM_START_STEPS  # per environment copy
    epochs: int = 8
    batch_size: int = 4096
    learning_rate: float = 1e-3
    preset: str = "pid"
    # Exploration after the fit: gSDE's default (−1) is sized for a random network; on a
    # network that already flies, noise that large wipes out the fit within 0.25 M steps.
    log_std: float = -3.0

    def run(self, model, venv) -> dict:
        """Fit `model`'s actor and critic in place; `venv` is the training VecNormalize (its
        statistics are updated by these flights, as training would)."""
        batch = venv.unwrapped.batch
        teacher = PidTeacher(self.preset, venv.num_envs, batch.config.dt, batch.config.action_mapping)
        policy = model.policy
        obs_x: list[np.ndarray] = []
        act_y: list[np.ndarray] = []
        delay_z: list[np.ndarray] = []
        rets: list[np.ndarray] = []
        ret_x: list[np.ndarray] = []
        history: list[dict] = []
        for r in range(self.rounds):
            actor = quick_eval.sb3_actor(model) if r else None  # the network flies, the PID labels
            raw, labels, rewards, dones, delays = self._fly(venv, batch, teacher, actor)
            obs_x.append(raw.reshape(-1, raw.shape[-1]))
            act_y.append(labels.reshape(-1, 4))
            delay_z.append(delays.reshape(-1))
            ret, keep = returns_of(venv, rewards, dones, model.gamma)
            ret_x.append(raw[keep].reshape(-1, raw.shape[-1]))
            rets.append(ret[keep].reshape(-1))
            x, y = np.concatenate(obs_x), np.concatenate(act_y)
            loss = self._fit_actor(policy, venv, x, y)
            history.append({"round": r, "flown_by": "network" if r else "pid", "samples": len(x),
                            "actor_mse": loss, "reward_mean": float(rewards.mean())})
        vloss_before, vloss = fit_critic(policy, venv, np.concatenate(ret_x), np.concatenate(rets),
                                         self.epochs, self.batch_size, self.learning_rate)
        with torch.no_grad():
            policy.log_std.fill_(self.log_std)
        return {"rounds": self.rounds, "env_steps": self.rounds * self.steps_per_round * venv.num_envs,
                # raw observations, the teacher's actions, each sample's airframe loop delay
                # (ticks): not for the summary
                "dataset": (x, y, np.concatenate(delay_z)),
                "history": history,
                "critic_mse_before": vloss_before, "critic_mse": vloss, "preset": self.preset,
                "log_std": self.log_std}

    def _fly(self, venv, batch, teacher: PidTeacher, actor):
        """One round: `steps_per_round` steps of every copy; the raw observations, the PID's
        labels, the raw rewards, the episode ends and each step's airframe loop delay.
        `actor` (normalised obs → action) flies, or the PID when it is None."""
        n = venv.num_envs
        obs = venv.reset()
        delay = episode_delay_ticks(batch)
        teacher.reset(np.ones(n, dtype=bool), delay)
        raw_all = np.empty((self.steps_per_round, n, obs.shape[-1]), dtype=np.float32)
        labels = np.empty((self.steps_per_round, n, 4))
        rewards = np.empty((self.steps_per_round, n))
        dones = np.empty((self.steps_per_round, n), dtype=bool)
        delays = np.empty((self.steps_per_round, n), dtype=np.int8)
        for k in range(self.steps_per_round):
            raw = venv.get_original_obs()
            label = teacher.act(*teacher_inputs(batch, raw))
            action = label if actor is None else actor(obs)
            raw_all[k], labels[k], delays[k] = raw, label, delay
            obs, _, done, _ = venv.step(np.clip(action, -1.0, 1.0).astype(np.float32))
            rewards[k] = venv.get_original_reward()
            dones[k] = done
            if done.any():  # the copies done have begun new episodes
                delay = episode_delay_ticks(batch)
                teacher.reset(done, delay)
        return raw_all, labels, rewards, dones, delays

    def _fit_actor(self, policy, venv, raw: np.ndarray, labels: np.ndarray) -> float:
        x = torch.as_tensor(venv.normalize_obs(raw), dtype=torch.float32)
        y = torch.as_tensor(labels, dtype=torch.float32)
        squash = torch.tanh if policy.squash_output else torch.nn.Identity()  # the error in action units
        params = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters()]
        return _regress(lambda xb: squash(policy.action_net(policy.mlp_extractor.forward_actor(
            policy.extract_features(xb, policy.pi_features_extractor)))), params, x, y,
            self.epochs, self.batch_size, self.learning_rate)


def fit_critic(policy, venv, raw: np.ndarray, returns: np.ndarray, epochs: int, batch: int, lr: float
               ) -> tuple[float, float]:
    """The critic's squared error against `returns` of the raw observations `raw`, before and after
    Adam fits it to them."""
    x = torch.as_tensor(venv.normalize_obs(raw), dtype=torch.float32)
    y = torch.as_tensor(returns, dtype=torch.float32)[:, None]
    params = [*policy.mlp_extractor.value_net.parameters(), *policy.value_net.parameters()]
    return _regress(lambda xb: policy.value_net(policy.mlp_extractor.forward_critic(
        policy.extract_features(xb, policy.vf_features_extractor))), params, x, y,
        epochs, batch, lr, before=True)


def returns_of(venv, rewards: np.ndarray, dones: np.ndarray, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """The discounted returns of raw `rewards` (steps × copies) scaled as training scales them, and
    which steps have enough future behind them to be a fair target."""
    return _discounted(_normalised(venv, rewards), dones, gamma)


def _normalised(venv, rewards: np.ndarray) -> np.ndarray:
    """Rewards scaled as training scales them, by the statistics at the end of the flights."""
    return venv.normalize_reward(rewards) if venv.norm_reward else rewards


def _discounted(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns-to-go per copy (episode ends cut them), and which steps have enough future
    behind them (5 horizons: γ^(5/(1−γ)) < 1 %) to be a fair target."""
    ret = np.zeros_like(rewards)
    run = np.zeros(rewards.shape[1])
    for k in range(len(rewards) - 1, -1, -1):
        run = rewards[k] + gamma * run * ~dones[k]
        ret[k] = run
    tail = min(len(rewards) - 1, int(5 / max(1e-6, 1.0 - gamma)))
    keep = np.zeros(rewards.shape, dtype=bool)
    keep[: len(rewards) - tail] = True
    return ret, keep


def _regress(fn, params, x: torch.Tensor, y: torch.Tensor, epochs: int, batch: int, lr: float,
             before: bool = False):
    """Adam on the mean squared error of fn(x) against y; the final error (and with
    `before`, the error before fitting too)."""
    with torch.no_grad():
        start = float(torch.nn.functional.mse_loss(fn(x), y))
    opt = torch.optim.Adam(params, lr=lr)
    gen = torch.Generator().manual_seed(0)
    loss = torch.tensor(float("nan"))
    for _ in range(epochs):
        for idx in torch.randperm(len(x), generator=gen).split(batch):
            loss = torch.nn.functional.mse_loss(fn(x[idx]), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        end = float(torch.nn.functional.mse_loss(fn(x), y))
    return (start, end) if before else end
