"""A short real training run: layout, export, flight in the firmware, and the in-training evaluator."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation import bar
from fcemu.evaluation.metrics import AXES, compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.neural import NeuralRateController
from fcemu.training import quick_eval
from fcemu.training.train import TrainConfig, train

pytestmark = [pytest.mark.slow, pytest.mark.no_wall_clock]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("train") / "smoke"
    cfg = TrainConfig(algo="ppo", steps=4096, seed=3, out=str(out), envs=8, checkpoint_every=2048,
                      eval_every=2048, eval_commands=4, eval_episodes=3, action_rate_penalty=0.1,
                      hp={"n_steps": 128, "batch_size": 256})  # with the default progress bar (needs rich)
    return out, train(cfg)


def test_run_layout(run):
    out, summary = run
    for name in ("config.json", "model.zip", "vecnormalize.pkl", "policy.onnx", "summary.json", "eval.json",
                 "report/report.md"):
        assert (out / name).is_file(), name
    for steps in (2048, 4096):
        assert (out / "checkpoints" / f"ppo_{steps}_steps.zip").is_file()
        assert (out / "checkpoints" / f"ppo_vecnormalize_{steps}_steps.pkl").is_file()
    assert any((out / "tb").rglob("events.out.tfevents.*"))
    config = json.loads((out / "config.json").read_text())
    assert config["algo"] == "ppo" and config["seed"] == 3 and config["trained_steps"] == 4096
    assert config["action_mapping"] == "throttle" and config["throttle"] == [0.5, 0.9]
    assert config["observation"]["memory"] == 1 and config["loop_rate_hz"] == 1000.0
    assert config["env"]["action_rate_penalty"] == 0.1
    assert summary["export"]["parity_ok"] and summary["steps"] == 4096
    assert config["hyperparameters"]["use_sde"] is True


def test_final_evaluation_flies_the_export_and_the_pids_on_the_same_commands(run):
    out, _ = run
    payload = json.loads((out / "eval.json").read_text())
    assert [r["controller"] for r in payload["results"]] == ["pid", "pid:paper", str(out / "policy.onnx")]
    assert all(r["episodes"] == 3 and r["seed"] == payload["seed"] for r in payload["results"])
    verdict = payload["bar"]
    assert verdict["best_pid"] in ("pid", "pid:paper") and verdict["meets_bar"] is False
    assert verdict["error_ratio"] == pytest.approx(verdict["policy_error_sum"] / verdict["pid_error_sum"])


def test_in_training_evaluation_exports_its_best_checkpoint(run):
    out, summary = run
    evals = summary["in_training_evals"]
    assert [e["steps"] for e in evals] == [2048, 4096]
    best = min(evals, key=quick_eval.selection_key)
    assert summary["exported"] == str(out / "checkpoints" / f"ppo_{best['steps']}_steps.zip")
    meta = NeuralRateController(out / "policy.onnx").metadata
    assert meta["training_steps"] == str(best["steps"])  # the checkpoint's own step count
    assert all(set(e["checks"]) == {"error_ratio", "rise", "peak", "success", "smoothness"} for e in evals)


def test_reward_terms_are_logged_separately(run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, _ = run
    acc = EventAccumulator(str(next((out / "tb").iterdir())))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    assert "reward/paper" in tags and "reward/action_rate" in tags
    assert "reward/tracking" in tags and "reward/action_rate_term" in tags
    assert all(e.value <= 0.0 for e in acc.Scalars("reward/action_rate_term"))
    assert all(e.value <= 0.0 for e in acc.Scalars("reward/paper"))
    assert all(e.value >= 0.0 for e in acc.Scalars("reward/action_rate"))
    lr = [e.value for e in acc.Scalars("train/learning_rate")]
    assert lr[0] <= 3e-4 and lr[-1] < lr[0]  # "lin_3e-4": decays linearly over the run


def test_exported_policy_flies_in_the_firmware(run):
    out, _ = run
    ctrl = NeuralRateController(out / "policy.onnx")
    assert ctrl.action_mapping == "throttle"
    traces = run_controller(str(out / "policy.onnx"), EvalConfig(episodes=3, seed=5), progress=False)
    assert traces.extra["controller_faults"] == 0  # the policy itself flew every tick
    assert np.isfinite(traces.rate).all() and traces.pwm.min() >= 1000 and traces.pwm.max() <= 2000
    assert np.ptp(traces.pwm) > 0  # it did command the motors


def test_batched_evaluation_matches_the_firmware_loop(run):
    """The in-training evaluator scores a policy as `fcemu eval` does, on the same commands."""
    out, _ = run
    policy = NeuralRateController(out / "policy.onnx")
    evaluator = quick_eval.BatchedEvaluator(3, seed=11)
    batched = evaluator.traces(lambda obs: np.stack([policy.infer(o).copy() for o in obs]))
    parts = [run_controller(str(out / "policy.onnx"), EvalConfig(episodes=1, seed=11 + i), progress=False)
             for i in range(3)]
    loop = quick_eval.concat_traces(parts, "onnx", 11)
    np.testing.assert_array_equal(batched.setpoint, loop.setpoint)
    np.testing.assert_allclose(batched.rate, loop.rate, atol=1e-6)
    np.testing.assert_allclose(batched.pwm, loop.pwm, atol=1e-3)
    a, b = compute_metrics(batched), compute_metrics(loop)
    for axis in AXES:
        assert a.stat("error", axis).mean == pytest.approx(b.stat("error", axis).mean, rel=1e-6)


def test_bar_verdict_names_each_criterion(run):
    out, _ = run
    traces = run_controller(str(out / "policy.onnx"), EvalConfig(episodes=4, seed=2), progress=False)
    pid = run_controller("pid", EvalConfig(episodes=4, seed=2), progress=False)
    verdict = bar.bar_verdict(compute_metrics(traces), {"pid": compute_metrics(pid)})
    assert set(verdict["checks"]) == {"error_ratio", "rise", "peak", "success", "smoothness"}
    assert verdict["meets_bar"] is False  # 4096 steps of training do not beat a PID
    assert verdict["error_ratio"] > 1.0
    same = bar.bar_verdict(compute_metrics(pid), {"pid": compute_metrics(pid)})
    assert same["error_ratio"] == 1.0 and not same["checks"]["error_ratio"] and same["checks"]["rise"]
    assert same["checks"]["peak"] and same["checks"]["smoothness"] and same["smoothness_ratio"] == 1.0


def test_unclipped_reward_weights_the_axes_and_never_saturates():
    from fcemu.training.train import make_vec_env

    venv = make_vec_env(TrainConfig(envs=2, seed=0, throttle=0.7, action_rate_penalty=0.5,
                                    axis_weights=(1.0, 2.0, 3.0)))
    venv.reset()
    spin = np.array([[1.0, -1.0, 1.0, -1.0]] * 2, dtype=np.float32)  # full differential: spins up
    for _ in range(400):
        _, reward, _, _ = venv.step(spin)
    info = venv.unwrapped.last_info
    e = np.abs(info["setpoint"] - info["rate"])
    expected = -(e[:, 0] + 2 * e[:, 1] + 3 * e[:, 2]) / (3 * 5.24) - 0.5 * info["action_rate"]
    np.testing.assert_allclose(reward, expected, rtol=1e-6)
    assert (info["paper_reward"] == -1.0).all() and (reward < -1.0).all()  # the paper's clip would hide this
    with pytest.raises(ValueError, match="unclipped"):
        TrainConfig(reward="paper", axis_weights=(1.0, 1.0, 2.0))
    venv.close()


def test_gym_make_with_the_training_env_kwargs_gives_the_training_reward():
    import gymnasium as gym

    from fcemu.training.train import make_vec_env

    cfg = TrainConfig(envs=2, seed=6, action_rate_penalty=2.0, axis_weights=(1.0, 1.0, 2.0))
    venv = make_vec_env(cfg)
    venv.reset()
    env = gym.make("fcemu/RateEpisodic-v0", **cfg.env_kwargs())
    env.reset(seed=cfg.seed)  # copy 0 of the batch follows the single env seeded with the batch's seed
    rng = np.random.default_rng(0)
    for _ in range(300):
        actions = rng.uniform(-1, 1, (2, 4)).astype(np.float32)
        _, rewards, _, _ = venv.step(actions)
        _, reward, *_ = env.step(actions[0])
        assert np.float32(reward) == rewards[0]
    assert rewards[0] != np.float32(venv.unwrapped.last_info["paper_reward"][0])  # not the paper's reward
    venv.close()


def test_a_randomised_run_trains_end_to_end_and_races_on_the_nominal_airframe(tmp_path):
    out = tmp_path / "rand"
    cfg = TrainConfig(algo="ppo", steps=2048, seed=1, out=str(out), envs=8, checkpoint_every=2048,
                      eval_every=2048, eval_commands=2, eval_episodes=0, randomize="iris", progress=False,
                      hp={"n_steps": 128, "batch_size": 256})
    summary = train(cfg)
    assert json.loads((out / "config.json").read_text())["env"]["randomize"] == "iris"
    assert summary["export"]["parity_ok"] and len(summary["in_training_evals"]) == 1
    assert "smoothness_ratio" in summary["in_training_evals"][0]


def test_the_race_flies_the_training_airframe():
    from fcemu.training.train import PidRaceCallback

    race = PidRaceCallback(TrainConfig(airframe="iris_realistic", eval_commands=2), every=1000)
    assert race.evaluator.env.config.base_airframe.name == "iris_realistic"
    assert race.evaluator.env.config.randomize is None
    nominal = quick_eval.pid_references(("pid",), 2, 1)["pid"]
    assert bar.error_sum(race.pids["pid"]) != bar.error_sum(nominal)


def test_an_airframe_without_a_tuned_pid_is_refused_before_training_when_the_run_compares_with_it(tmp_path):
    from fcemu.firmware.controllers import ControllerSpecError
    from fcemu.sim_bridge.airframe import AIRFRAME_DIR

    raw = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    raw["name"] = "untuned_quad"
    path = tmp_path / "untuned_quad.json"
    path.write_text(json.dumps(raw))
    out = tmp_path / "run"
    with pytest.raises(ControllerSpecError, match="no PID tuned for untuned_quad"):
        train(TrainConfig(airframe=str(path), steps=64, envs=2, out=str(out), progress=False))
    assert not out.exists()  # nothing trained, nothing written


def test_the_batched_evaluator_observes_with_the_trained_leaks():
    """The race scores a policy on the observation it was trained on, leaks included."""
    from fcemu.firmware.observation import FIELDS, INTEGRAL, RMS

    fields = (*FIELDS, INTEGRAL, RMS)
    evaluator = quick_eval.BatchedEvaluator(2, 3, memory=2, obs_fields=fields, integral_leak=0.99,
                                            rms_leak=0.9)
    spec = evaluator.env.config.observation_spec
    assert (spec.fields, spec.integral_leak, spec.rms_leak) == (fields, 0.99, 0.9)
    evaluator.close()


def test_init_fine_tunes_the_trained_networks_and_statistics(run, tmp_path):
    import pickle

    from stable_baselines3 import PPO

    src, _ = run
    cfg = TrainConfig(algo="ppo", steps=1024, seed=5, out=str(tmp_path / "ft"), envs=8,
                      checkpoint_every=10**9, eval_episodes=0, action_rate_penalty=0.1, progress=False,
                      init=str(src),
                      hp={"n_steps": 128, "batch_size": 256, "learning_rate": 0.0})
    train(cfg)
    config = json.loads((tmp_path / "ft" / "config.json").read_text())
    assert config["init"] == str(src / "model.zip") and config["trained_steps"] == 1024
    before = PPO.load(src / "model.zip", device="cpu").policy.state_dict()
    after = PPO.load(tmp_path / "ft" / "model.zip", device="cpu").policy.state_dict()
    assert before.keys() == after.keys()
    for key in before:  # learning rate 0: the loaded networks, unchanged by the updates
        assert np.array_equal(before[key].numpy(), after[key].numpy()), key
    with open(src / "vecnormalize.pkl", "rb") as fh:
        then = pickle.load(fh).obs_rms
    with open(tmp_path / "ft" / "vecnormalize.pkl", "rb") as fh:
        now = pickle.load(fh).obs_rms
    # the statistics went on from the run's: 1024 steps and each of the 8 twins' first observation
    assert now.count == pytest.approx(then.count + 1024 + 8)


def test_init_from_a_distilled_student_fits_its_critic_and_keeps_its_statistics(run, tmp_path):
    """A student of `fcemu distill` has an actor and the statistics it was fitted through, but a
    critic as drawn: the fine-tune fits the critic on the student's flights and leaves the rest;
    with --anchor those flights are what PPO is held to."""
    import pickle

    from stable_baselines3 import PPO

    from fcemu.training.distill import DistillConfig, distill

    src, _ = run
    student = tmp_path / "student"
    distill(DistillConfig(teacher=str(src / "policy.onnx"), out=str(student), net_arch=(16, 16), rounds=1,
                          steps=60, envs=4, fit_steps=20, batch_size=256, threads=1, progress=False))
    net = {"net_arch": {"pi": [16, 16], "vf": [64, 64]}, "log_std_init": -3.0}
    summary = train(TrainConfig(algo="ppo", steps=1024, seed=5, out=str(tmp_path / "ft"), envs=8,
                                checkpoint_every=10**9, eval_episodes=0, obs_clip=0.0, progress=False,
                                init=str(student), anchor=1.0,
                                hp={"n_steps": 128, "batch_size": 256, "learning_rate": 0.0,
                                    "policy_kwargs": net}))
    critic = summary["init_critic"]
    assert critic["env_steps"] == 1500 * 8 and critic["critic_mse"] < 0.5 * critic["critic_mse_before"]
    assert summary["init_anchor_samples"] == 1500 * 8
    before = PPO.load(student / "model.zip", device="cpu").policy.state_dict()
    after = PPO.load(tmp_path / "ft" / "model.zip", device="cpu").policy.state_dict()
    value = [key for key in before if "value" in key]
    assert value and any(not np.array_equal(before[k].numpy(), after[k].numpy()) for k in value)
    for key in before.keys() - set(value):  # learning rate 0: the actor as distilled
        assert np.array_equal(before[key].numpy(), after[key].numpy()), key
    with open(student / "vecnormalize.pkl", "rb") as fh:
        then = pickle.load(fh).obs_rms
    with open(tmp_path / "ft" / "vecnormalize.pkl", "rb") as fh:
        now = pickle.load(fh).obs_rms
    assert np.array_equal(then.mean, now.mean) and np.array_equal(then.var, now.var)


def test_init_adds_an_observation_field_at_zero_weight(run, tmp_path):
    """A fine-tune with --motor-output from a run without it: the loaded networks compute what
    they did (the new inputs' weights are zero), and the new inputs are normalised from flight."""
    import pickle

    from stable_baselines3 import PPO

    src, _ = run
    out = tmp_path / "widened"
    train(TrainConfig(algo="ppo", steps=1024, seed=5, out=str(out), envs=8, checkpoint_every=10**9,
                      eval_episodes=0, action_rate_penalty=0.1, progress=False, init=str(src),
                      motor_output=True, hp={"n_steps": 128, "batch_size": 256, "learning_rate": 0.0}))
    config = json.loads((out / "config.json").read_text())
    assert config["init_added_fields"] == ["motor_output"]
    assert config["observation"]["fields"] == ["rate_error", "rotor_speed", "motor_output"]
    before = PPO.load(src / "model.zip", device="cpu").policy.state_dict()
    after = PPO.load(out / "model.zip", device="cpu").policy.state_dict()
    for key in before:
        if key.endswith("_net.0.weight"):  # the actor's and the critic's input layers: 7 columns → 11
            assert after[key].shape == (before[key].shape[0], 11), key
            assert np.array_equal(after[key][:, :7].numpy(), before[key].numpy()), key
            assert not after[key][:, 7:].any(), key
        else:
            assert np.array_equal(before[key].numpy(), after[key].numpy()), key
    with open(out / "vecnormalize.pkl", "rb") as fh:
        rms = pickle.load(fh).obs_rms
    assert rms.mean.shape == (11,)
    assert (0.0 < rms.mean[7:]).all() and (rms.mean[7:] < 1.0).all() and (rms.var[7:] > 0.0).all()
    assert json.loads((out / "summary.json").read_text())["export"]["parity_ok"]


def test_init_refuses_a_run_of_another_observation_or_algorithm(run, tmp_path):
    from fcemu.training.train import InitError

    src, _ = run
    base = dict(steps=128, seed=5, envs=8, eval_episodes=0, progress=False,
                hp={"n_steps": 16, "batch_size": 128})
    with pytest.raises(InitError, match="observation"):
        train(TrainConfig(algo="ppo", memory=2, out=str(tmp_path / "m2"), init=str(src), **base))
    assert not (tmp_path / "m2").exists()  # refused before anything was written
    with pytest.raises(InitError, match="trained by 'ppo'"):
        train(TrainConfig(algo="trpo", out=str(tmp_path / "trpo"), init=str(src), **base))
    with pytest.raises(InitError, match="no such checkpoint"):
        missing = src / "checkpoints" / "ppo_1_steps.zip"
        train(TrainConfig(algo="ppo", out=str(tmp_path / "none"), init=str(missing), **base))


def test_a_pool_of_quads_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match="distill inversion --airframe-pool"):
        train(TrainConfig(airframe_pool="draw:2:1", out=str(tmp_path / "run")))
    assert not (tmp_path / "run").exists()
