"""Fine-tuning (`fcemu train --init RUN|ZIP`): start from a trained run instead of fresh networks.

The run's networks, Adam state and VecNormalize statistics are loaded into the new model. The
run must have observed what this one does, less any fields this one adds: a fine-tune may
*add* fields (e.g. `--motor-output` to a policy trained without it). An added field's columns get
zero input weights, so the loaded policy and critic compute exactly what they did, and PPO
learns from there whether to use them. Their normalisation statistics are measured on the
loaded policy's own flights before training (its actions do not depend on them, the weights
being zero), so the new inputs start normalised like the others rather than at a guess.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.vec_env import VecNormalize

from fcemu.export.onnx_export import Checkpoint, ExportError, find_checkpoint
from fcemu.firmware.observation import ObservationSpec

MEASURE_STEPS = 500  # per twin: the flights an added field's statistics are measured on
CRITIC_STEPS = 1500  # per twin: the flights a distilled student's critic is fitted on


class FixedMeanStd(RunningMeanStd):
    """Observation statistics that training does not update: a distilled student's weights were
    fitted through these very statistics, so letting them drift to the fine-tune's flights would
    change what the network computes before PPO has learnt anything."""

    def update(self, arr: np.ndarray) -> None:
        pass


class InitError(ValueError):
    """`--init` names a run this one cannot start from."""


@dataclass(frozen=True)
class InitSource:
    """The checkpoint `--init` names, and how its observation maps onto this run's."""

    checkpoint: Checkpoint
    theirs: ObservationSpec
    ours: ObservationSpec

    @property
    def distilled(self) -> bool:
        """A student of `fcemu distill`: its actor fitted, its critic as drawn."""
        return "distill" in self.checkpoint.config

    @property
    def added(self) -> tuple[str, ...]:
        return tuple(f for f in self.ours.fields if f not in self.theirs.fields)

    def column_map(self) -> np.ndarray:
        """For each of our observation's columns, the run's column it was, or −1 (added)."""
        theirs = {name: cols for name, (cols, _, _)
                  in zip(self.theirs.fields, self.theirs.layout, strict=True)}
        step = np.full(self.ours.step_size, -1)
        for name, (cols, _, _) in zip(self.ours.fields, self.ours.layout, strict=True):
            if name in theirs:
                step[cols] = np.arange(theirs[name].start, theirs[name].stop)
        # newest first, one step after another (firmware.observation.ObservationHistory)
        k = np.arange(self.ours.memory)[:, None]
        return np.where(step >= 0, k * self.theirs.step_size + step, -1).reshape(-1)


def _spec(raw: Any) -> ObservationSpec:
    return ObservationSpec.from_json(json.dumps(raw))


def init_checkpoint(target: str, config: dict[str, Any]) -> InitSource:
    """The run `--init` names, checked against this run's `config` before anything is built.

    Same algorithm, and the same observation (memory, scales, leaks) up to fields this run
    adds: a network is only meaningful on the inputs it was trained on, so a mismatch is an
    error here rather than a run that learns from scratch on garbage.
    """
    try:
        checkpoint = find_checkpoint(target)
    except ExportError as exc:
        raise InitError(f"--init {target}: {exc}") from None
    theirs_raw = checkpoint.config
    if theirs_raw.get("algo") != config["algo"]:
        raise InitError(f"--init {target}: trained by {theirs_raw.get('algo')!r}, "
                        f"this run is {config['algo']!r}")
    ours = _spec(config["observation"])
    try:
        theirs = _spec(theirs_raw["observation"])
    except (KeyError, TypeError, ValueError):
        theirs = None
    if (theirs is None or not set(theirs.fields) <= set(ours.fields)
            or dataclasses.replace(ours, fields=theirs.fields).to_json() != theirs.to_json()):
        raise InitError(f"--init {target}: its observation {theirs_raw.get('observation')} is not this run's "
                        f"{config['observation']} (give the same --memory, --integral, --error-rms, ...; "
                        "a fine-tune may only add fields)")
    return InitSource(checkpoint, theirs, ours)


def _widen(saved: torch.Tensor, like: torch.Tensor, columns: np.ndarray, size: int) -> torch.Tensor:
    """A first-layer matrix (or its Adam moment) on our columns: the run's (of `size` inputs),
    zero where added."""
    if saved.shape == like.shape or saved.shape != (like.shape[0], size) or like.shape[1:] != (len(columns),):
        return saved  # not an input layer: set_parameters compares it as it is
    out = torch.zeros(like.shape, dtype=saved.dtype)
    kept = np.flatnonzero(columns >= 0)
    out[:, torch.as_tensor(kept)] = saved[:, torch.as_tensor(columns[kept])]
    return out


def _measure(model, venv: VecNormalize, columns: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of raw observation `columns` on `steps` of the model's own flights."""
    venv.training = False  # the placeholder statistics must not be averaged in
    obs, raw = venv.reset(), []
    for _ in range(steps):
        actions, _ = model.predict(obs, deterministic=False)
        obs, *_ = venv.step(actions)
        raw.append(venv.get_original_obs()[:, columns])
    venv.training = True
    values = np.concatenate(raw).astype(np.float64)
    return values.mean(axis=0), values.var(axis=0)


def start_from(model, venv: VecNormalize, source: InitSource, measure_steps: int = MEASURE_STEPS) -> None:
    """The checkpoint's networks and Adam state into `model`, its observation and return
    statistics into `venv` (they go on updating); added fields as the module says."""
    path = source.checkpoint.model_path
    columns, size = source.column_map(), source.theirs.size
    _, params, _ = load_from_zip_file(path, device="cpu")
    if params is None or "policy" not in params:
        raise InitError(f"--init {path}: no policy parameters in it")
    ours = model.policy.state_dict()
    params["policy"] = {k: _widen(v, ours[k], columns, size) if k in ours else v
                        for k, v in params["policy"].items()}
    optimizer = params.get("policy.optimizer")
    if optimizer is not None:
        for index, like in enumerate(model.policy.parameters()):
            for moment in ("exp_avg", "exp_avg_sq"):
                state = optimizer["state"].get(index, {})
                if moment in state:
                    state[moment] = _widen(state[moment], like.detach(), columns, size)
    try:
        model.set_parameters(params, exact_match=True, device="cpu")
    except (RuntimeError, ValueError, KeyError) as exc:  # torch's size mismatch, SB3's missing keys
        raise InitError(f"--init {path}: its networks do not fit this run's ({exc})") from None
    if source.checkpoint.vecnormalize_path is None:
        return
    with open(source.checkpoint.vecnormalize_path, "rb") as fh:
        saved = pickle.load(fh)
    venv.ret_rms = saved.ret_rms
    rms = (FixedMeanStd if source.distilled else RunningMeanStd)(shape=columns.shape)
    venv.obs_rms = rms
    if not source.added:
        rms.mean, rms.var, rms.count = saved.obs_rms.mean, saved.obs_rms.var, saved.obs_rms.count
        return
    kept, added = np.flatnonzero(columns >= 0), np.flatnonzero(columns < 0)
    rms.mean[kept], rms.var[kept] = saved.obs_rms.mean[columns[kept]], saved.obs_rms.var[columns[kept]]
    rms.count = saved.obs_rms.count
    if venv.norm_obs:
        rms.mean[added], rms.var[added] = _measure(model, venv, added, measure_steps)


@dataclass(frozen=True)
class OwnFlights:
    """The loaded policy's flights in this run's environment, (steps, n_envs, ...) each."""

    raw_obs: np.ndarray
    actions: np.ndarray  # the policy's mean actions, before the environment's clip
    rewards: np.ndarray
    dones: np.ndarray

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(raw observations, actions) flattened: what `--anchor` holds the fine-tune to."""
        width = self.raw_obs.shape[-1], self.actions.shape[-1]
        return self.raw_obs.reshape(-1, width[0]), self.actions.reshape(-1, width[1])


def fly_own_flights(model, venv: VecNormalize, steps: int = CRITIC_STEPS) -> OwnFlights:
    """`steps` steps of every twin flown by the loaded policy, deterministically."""
    from fcemu.training.quick_eval import sb3_actor

    actor, obs = sb3_actor(model), venv.reset()
    raw = np.empty((steps, venv.num_envs, obs.shape[-1]), dtype=np.float32)
    actions = np.empty((steps, venv.num_envs, model.action_space.shape[0]), dtype=np.float32)
    rewards = np.empty((steps, venv.num_envs))
    dones = np.empty((steps, venv.num_envs), dtype=bool)
    for k in range(steps):
        raw[k], actions[k] = venv.get_original_obs(), actor(obs)
        obs, _, dones[k], _ = venv.step(np.clip(actions[k], -1.0, 1.0))
        rewards[k] = venv.get_original_reward()
    return OwnFlights(raw, actions, rewards, dones)


def fit_critic_on_own_flights(model, venv: VecNormalize, flights: OwnFlights) -> dict[str, Any]:
    """The critic fitted to the discounted returns of the loaded policy's own flights: a distilled
    student's critic is as it was drawn, and PPO's first advantages against it would be noise that
    moves the actor away from what it was taught."""
    from fcemu.training.warm_start import WarmStart, fit_critic, returns_of

    returns, keep = returns_of(venv, flights.rewards, flights.dones, model.gamma)
    fit = WarmStart()
    before, after = fit_critic(model.policy, venv, flights.raw_obs[keep], returns[keep], fit.epochs,
                               fit.batch_size, fit.learning_rate)
    return {"env_steps": flights.rewards.size, "critic_mse_before": before, "critic_mse": after}
