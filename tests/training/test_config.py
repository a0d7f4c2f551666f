"""`TrainConfig`, declared once: `fcemu train`, `bench train` and `sweep` options are generated from it."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fcemu.cli import build_parser
from fcemu.training.config import ALGOS, FIELDS, WARM_START_TARGET_KL, TrainConfig, from_args, parse_hp

pytestmark = pytest.mark.no_wall_clock

ROOT = Path(__file__).resolve().parents[2]


def _flags(argv: list[str]) -> set[str]:
    parser = build_parser()
    sub = parser._subparsers._group_actions[0].choices
    for name in argv:
        sub = sub[name]
        if name != argv[-1]:
            sub = sub._subparsers._group_actions[0].choices
    return {opt for action in sub._actions for opt in action.option_strings}


def test_every_field_is_a_train_option_with_its_help():
    flags = _flags(["train"])
    for name, f in FIELDS.items():
        assert "--" + name.replace("_", "-") in flags, name
        assert f.metadata["help"], name
    assert {"--no-progress", "--no-squash", "--no-norm-obs", "--json"} <= flags
    algo = next(a for a in build_parser()._subparsers._group_actions[0].choices["train"]._actions
                if a.dest == "algo")
    assert tuple(algo.choices) == tuple(ALGOS)  # the algorithm list lives in ALGOS only


def test_bench_and_sweep_take_the_same_options():
    fields = {"--" + n.replace("_", "-") for n in FIELDS}
    assert fields - _flags(["bench", "train"]) == {"--eval-seed", "--export", "--progress"}
    assert fields - _flags(["sweep"]) == {"--seed", "--threads", "--progress"}  # --out, --hp: its own
    assert {"--seeds", "--out", "--hp", "--config", "--address", "--json"} <= _flags(["sweep"])


def test_the_command_line_builds_the_config():
    argv = "train --algo sac --memory 3 --steps 10 --seed 4 --envs 2 --out runs/x --throttle 0.6 0.8"
    args = build_parser().parse_args(argv.split())
    assert args.handler == "fcemu.training.train:train_command"
    cfg = from_args(args)
    got = (cfg.algo, cfg.memory, cfg.steps, cfg.seed, cfg.n_envs, cfg.throttle, cfg.out)
    assert got == ("sac", 3, 10, 4, 2, (0.6, 0.8), "runs/x")
    assert cfg.obs_fields == ("rate_error", "rotor_speed") and "integral" not in argv
    cfg = from_args(build_parser().parse_args([*argv.split(), "--integral", "--throttle", "0.7"]))
    assert cfg.obs_fields[-1] == "rate_error_integral" and cfg.env_kwargs()["obs_fields"] == cfg.obs_fields
    assert cfg.env_kwargs()["integral_leak"] == 0.995
    with pytest.raises(ValueError, match="integral-leak"):
        from_args(build_parser().parse_args([*argv.split(), "--integral", "--integral-leak", "1.0"]))
    with pytest.raises(ValueError, match="needs --integral"):  # would be ignored: no integral to leak
        from_args(build_parser().parse_args([*argv.split(), "--integral-leak", "0.9995"]))
    assert cfg.obs_clip == 10.0
    assert from_args(build_parser().parse_args([*argv.split(), "--obs-clip", "0"])).obs_clip == 0.0
    for bad in ("-1", "inf", "nan"):
        with pytest.raises(ValueError, match="obs-clip"):
            from_args(build_parser().parse_args([*argv.split(), "--obs-clip", bad]))
    rms = ["--integral", "--error-rms", "--rms-leak", "0.99"]
    cfg = from_args(build_parser().parse_args([*argv.split(), *rms]))
    assert cfg.obs_fields[-2:] == ("rate_error_integral", "rate_error_rms")
    assert cfg.env_kwargs()["rms_leak"] == 0.99 == cfg.obs_leaks["rms_leak"]
    with pytest.raises(ValueError, match="needs --error-rms"):
        from_args(build_parser().parse_args([*argv.split(), "--rms-leak", "0.99"]))
    cfg = from_args(build_parser().parse_args([*argv.split(), "--integral", "--throttle", "0.7"]))
    assert cfg.throttle == 0.7
    with pytest.raises(ValueError, match="squash"):
        from_args(build_parser().parse_args([*argv.split(), "--squash"]))  # SAC squashes already
    ppo = from_args(build_parser().parse_args(["train", "--squash", "--action-rate-penalty", "2",
                                               "--hp", "gamma=0.97", "--no-progress"]))
    assert ppo.hyper["policy_kwargs"]["squash_output"] and ppo.hyper["use_sde"] and ppo.hyper["gamma"] == 0.97
    assert ppo.out == "runs/ppo" and not ppo.progress
    default = from_args(build_parser().parse_args(["train"]))
    assert dataclasses.asdict(default) == dataclasses.asdict(TrainConfig())
    bench = build_parser().parse_args(["bench", "train", "--budget-s", "60", "--hp", "n_epochs=1"])
    assert bench.handler == "fcemu.benchmarks.train:bench_train" and bench.budget_s == 60.0
    cfg = from_args(bench)
    assert (cfg.steps, cfg.eval_every, cfg.eval_episodes, cfg.hyper["n_epochs"]) == (10**7, 250_000, 0, 1)


def test_validation():
    with pytest.raises(ValueError, match="unknown algorithm"):
        TrainConfig(algo="a2c")
    with pytest.raises(ValueError, match="unknown reward"):
        TrainConfig(reward="shaped")
    with pytest.raises(ValueError, match="throttle"):
        TrainConfig(throttle=(0.5, 0.6, 0.7))
    assert parse_hp(["gamma=0.97", "n_steps=64", "net=[32, 32]", "name=x"]) == {
        "gamma": 0.97, "n_steps": 64, "net": [32, 32], "name": "x"}
    with pytest.raises(ValueError, match="key=value"):
        parse_hp(["gamma"])
    assert "squash_output" not in TrainConfig().hyper["policy_kwargs"]
    with pytest.raises(ValueError, match="--jobs"):
        TrainConfig(threads=-1)


def test_a_warm_started_ppo_run_limits_its_updates_by_kl_unless_told_otherwise():
    assert "target_kl" not in TrainConfig().hyper
    assert TrainConfig(warm_start="pid").hyper["target_kl"] == WARM_START_TARGET_KL
    assert TrainConfig(warm_start="pid", hp={"target_kl": None}).hyper["target_kl"] is None
    assert TrainConfig(warm_start="pid", hp={"target_kl": 0.05}).hyper["target_kl"] == 0.05
    assert TrainConfig(algo="trpo", warm_start="pid").hyper["target_kl"] == 0.01  # TRPO's own trust region


def test_threads_default_to_the_cpus_this_process_may_use():
    assert TrainConfig().threads == len(os.sched_getaffinity(0))
    assert TrainConfig(threads=3).threads == 3
    one_cpu = subprocess.run(
        ["taskset", "-c", "0", sys.executable, "-c",
         "from fcemu.training.config import TrainConfig; print(TrainConfig().threads)"],
        env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=60)
    assert one_cpu.stdout.strip() == "1", one_cpu.stderr


def _fcemu(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, "-m", "fcemu", *args], env=env, capture_output=True, text=True,
                          timeout=120)


def test_a_bad_option_is_one_line_and_exit_2():
    for argv in (["train", "--throttle", "0.5", "0.6", "0.7"], ["train", "--hp", "gamma"],
                 ["sweep", "--seeds", "x-y"], ["sweep", "--eval-every", "0"]):
        proc = _fcemu(*argv)
        assert proc.returncode == 2 and proc.stderr.startswith("fcemu: error:"), (argv, proc.stderr)
        assert proc.stderr.count("\n") == 1 and proc.stdout == ""


def test_building_the_parsers_loads_neither_torch_nor_ray():
    code = ("import sys; from fcemu.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('torch', 'ray', 'mujoco', 'stable_baselines3') if m in sys.modules))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stderr


def test_randomize_reaches_the_training_env_and_is_off_by_default():
    assert "randomize" not in TrainConfig().env_kwargs()  # the nominal airframe, exactly as before
    cfg = from_args(build_parser().parse_args(["train", "--randomize", "iris"]))
    assert cfg.env_kwargs()["randomize"] == "iris"
    from fcemu.sim_bridge.vec_env import BatchedRateEnv

    env = BatchedRateEnv(2, **{**cfg.env_kwargs(), "episode_s": 0.01})
    env.reset(seed=0)
    assert {"mass", "tau_up", "gyro_noise_std", "esc_delay_ticks"} <= set(env.episode_factors[0])
    with pytest.raises(ValueError, match="no randomisation file"):
        TrainConfig(randomize="nosuch")
    with pytest.raises(ValueError, match="ranges are for airframe 'iris', not 'iris_realistic'"):
        TrainConfig(randomize="iris", airframe="iris_realistic")


def test_the_warm_starts_size_is_set_and_checked():
    cfg = TrainConfig(warm_start="pid", warm_start_rounds=5, warm_start_steps=3000)
    assert (cfg.warm_start_rounds, cfg.warm_start_steps) == (5, 3000)
    for bad in ({"warm_start_rounds": 0}, {"warm_start_steps": 0}):
        with pytest.raises(ValueError, match="must be >= 1"):
            TrainConfig(warm_start="pid", **bad)


def test_a_share_of_randomised_episodes_goes_to_the_env_and_needs_ranges():
    assert TrainConfig(randomize="iris", randomize_share=0.5).env_kwargs()["randomize_share"] == 0.5
    assert "randomize_share" not in TrainConfig(randomize="iris").env_kwargs()
    for bad in ({"randomize": "iris", "randomize_share": 2.0}, {"randomize_share": 0.5}):
        with pytest.raises(ValueError, match="--randomize-share"):
            TrainConfig(**bad)


def test_the_penalty_gate_goes_to_the_env_and_needs_the_penalty():
    kwargs = TrainConfig(action_rate_penalty=1.0, action_rate_after=0.2).env_kwargs()
    assert kwargs["action_rate_after_s"] == 0.2
    assert "action_rate_after_s" not in TrainConfig(action_rate_penalty=1.0).env_kwargs()
    with pytest.raises(ValueError, match="give the penalty too"):
        TrainConfig(action_rate_after=0.2)
    with pytest.raises(ValueError, match="action_rate_after_s"):
        TrainConfig(action_rate_penalty=1.0, action_rate_after=-0.2)


def test_init_and_warm_start_exclude_each_other():
    with pytest.raises(ValueError, match="--init"):
        TrainConfig(warm_start="pid", init="runs/ppo")
    assert TrainConfig(init="runs/ppo").hyper["target_kl"] == WARM_START_TARGET_KL  # refining, as after one


def test_training_maps_actions_as_the_env_does_by_default() -> None:
    from fcemu.firmware.action import DEFAULT_ACTION_MAPPING

    assert TrainConfig().action_mapping == DEFAULT_ACTION_MAPPING
