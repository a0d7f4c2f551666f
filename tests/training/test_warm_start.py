"""The PID teacher flies the training twin as the firmware flies the PID, and the warm
start leaves a network that flies close to it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from stable_baselines3.common.vec_env import VecNormalize

from fcemu.evaluation import bar
from fcemu.evaluation.metrics import compute_metrics
from fcemu.firmware.controllers import load_controller
from fcemu.training import quick_eval
from fcemu.training.config import TrainConfig
from fcemu.training.train import make_model, make_vec_env
from fcemu.training.warm_start import WarmStart
from fcemu.training.warm_start_teacher import PidTeacher, episode_delay_ticks, load_schedule, teacher_inputs


def _teacher_flight(n: int, seed: int):
    ev = quick_eval.BatchedEvaluator(n, seed)
    teacher = PidTeacher("pid", n, ev.env.config.dt)
    teacher.reset(np.ones(n, dtype=bool))
    return compute_metrics(ev.traces(lambda obs: teacher.act(*teacher_inputs(ev.env, obs)), "teacher"))


def test_the_teacher_on_the_batched_twin_flies_as_the_firmware_pid():
    n, seed = 6, 1
    teacher = bar.error_sum(_teacher_flight(n, seed))
    firmware = bar.error_sum(quick_eval.pid_references(("pid",), n, seed)["pid"])
    assert teacher == pytest.approx(firmware, rel=0.02)  # a sign or axis mix-up is many times off


@pytest.mark.slow
@pytest.mark.parametrize("squash", [False, True])
def test_warm_start_fits_the_network_to_fly_near_the_pid(tmp_path: Path, squash: bool):
    cfg = TrainConfig(seed=2, out=str(tmp_path), envs=16, progress=False, squash=squash)
    venv = VecNormalize(make_vec_env(cfg), norm_obs=True, norm_reward=True, clip_obs=10.0, gamma=0.99)
    model = make_model(cfg, venv, tmp_path / "tb")
    ev = quick_eval.BatchedEvaluator(8, 1)
    pid = bar.error_sum(quick_eval.pid_references(("pid",), 8, 1)["pid"])

    def ratio() -> float:
        return bar.error_sum(compute_metrics(ev.traces(quick_eval.sb3_actor(model, venv)))) / pid

    untrained = ratio()
    out = WarmStart(rounds=2, steps_per_round=1200).run(model, venv)
    assert out["env_steps"] == 2 * 1200 * 16
    assert [h["samples"] for h in out["history"]] == [1200 * 16, 2 * 1200 * 16]
    assert untrained > 5.0 and ratio() < 1.8  # this little data: 1.20 (1.59 squashed); full size 1.01-1.02
    assert out["critic_mse"] < 0.5 * out["critic_mse_before"]


@pytest.mark.slow
@pytest.mark.parametrize("algo, anchor", [("ppo", 1.0), ("trpo", 0.0)])
def test_train_with_a_warm_start_reports_it_and_its_time_counts_in_the_race(tmp_path: Path, algo: str,
                                                                           anchor: float):
    import json

    from fcemu.training.train import train

    out = tmp_path / "run"
    cfg = TrainConfig(algo=algo, seed=0, out=str(out), envs=8, steps=4096, checkpoint_every=100_000,
                      eval_every=2048, eval_commands=2, eval_episodes=0, warm_start="pid", select="error",
                      progress=False, anchor=anchor,
                      hp={"n_steps": 128, "batch_size": 256})
    summary = train(cfg)
    assert json.loads((out / "config.json").read_text()).get("anchor", 0.0) == anchor
    assert "dataset" not in json.loads((out / "summary.json").read_text())["warm_start"]
    warm = summary["warm_start"]
    assert warm["env_steps"] == 3 * 1500 * 8 and warm["preset"] == "pid"
    assert summary["steps"] == 4096  # the warm start's steps are not the algorithm's
    evals = summary["in_training_evals"]
    assert evals[0]["wall_s"] > warm["wall_s"]  # the race's clock ran through the warm start
    lowest = min(evals, key=lambda e: e["error_ratio"])  # --select error: however rough
    assert summary["exported"] == str(out / "checkpoints" / f"{algo}_{lowest['steps']}_steps.zip")


def test_the_teacher_must_be_a_pid():
    with pytest.raises(ValueError, match="teacher is a PID"):
        TrainConfig(warm_start="policies/iris_rate_ppo.onnx")
    with pytest.raises(ValueError, match="unknown PID preset"):
        TrainConfig(warm_start="pid:nope")
    with pytest.raises(ValueError, match="actor-critic"):
        TrainConfig(algo="sac", warm_start="pid")


def test_a_schedule_flies_each_copy_with_the_band_for_its_airframes_delay(tmp_path: Path):
    path = tmp_path / "two.json"
    path.write_text('{"bands": [{"from_delay_ticks": 0, "controller": "pid"},'
                    ' {"from_delay_ticks": 3, "controller": "pid:iris_robust"}]}')
    teacher = PidTeacher(f"schedule:{path}", 4, 0.001)
    assert [teacher.schedule.band(d) for d in (0, 2, 3, 5)] == [0, 0, 1, 1]
    teacher.reset(np.ones(4, dtype=bool), np.array([0, 2, 3, 5]))
    roll_kp = [c.pid.gains.kp[0] for c in teacher.ctrls]
    nominal, robust = (load_controller(s).pid.gains.kp[0] for s in ("pid", "pid:iris_robust"))
    assert roll_kp == pytest.approx([nominal, nominal, robust, robust]) and robust < nominal
    teacher.reset(np.array([False, False, True, False]), np.array([9, 9, 1, 9]))  # only copy 2 starts anew
    assert [c.pid.gains.kp[0] for c in teacher.ctrls] == pytest.approx([nominal, nominal, nominal, robust])
    with pytest.raises(ValueError, match="needs each episode's delay_ticks"):
        teacher.reset(np.ones(4, dtype=bool))


def test_the_delay_of_each_episode_is_the_drawn_airframes():
    from fcemu.sim_bridge.vec_env import BatchedRateEnv

    batch = BatchedRateEnv(8, randomize="iris")
    batch.reset(seed=3)
    drawn = [f["esc_delay_ticks"] + f["gyro_delay_ticks"] for f in batch.episode_factors]
    assert episode_delay_ticks(batch).tolist() == drawn and len(set(drawn)) > 1
    nominal = BatchedRateEnv(2)
    nominal.reset(seed=3)
    assert episode_delay_ticks(nominal).tolist() == [0, 0]


@pytest.mark.parametrize("bands, match", [
    ('[{"from_delay_ticks": 1, "controller": "pid"}]', "start at 0"),
    ('[{"from_delay_ticks": 0, "controller": "pid"}, {"from_delay_ticks": 0, "controller": "pid"}]', "rise"),
    ('[{"from_delay_ticks": 0, "controller": "policies/iris_rate_ppo.onnx"}]', "teacher is a PID"),
    ('[{"from_delay_ticks": 0}]', "cannot read"),
    ('[]', "at least one band"),
])
def test_a_bad_schedule_is_refused_with_the_reason(tmp_path: Path, bands: str, match: str):
    path = tmp_path / "bad.json"
    path.write_text(f'{{"bands": {bands}}}')
    with pytest.raises(ValueError, match=match):
        TrainConfig(warm_start=f"schedule:{path}")


def test_the_shipped_schedule_is_a_teacher_and_an_unknown_one_names_the_shipped():
    assert load_schedule("schedule:latency").controllers[0] == "pid"
    TrainConfig(warm_start="schedule:latency")
    with pytest.raises(ValueError, match="shipped: latency"):
        TrainConfig(warm_start="schedule:nope")


def test_each_warm_start_sample_carries_its_airframes_delay(tmp_path: Path):
    cfg = TrainConfig(seed=1, out=str(tmp_path), envs=6, progress=False, randomize="iris")
    venv = VecNormalize(make_vec_env(cfg), norm_obs=True, norm_reward=True, clip_obs=10.0, gamma=0.99)
    model = make_model(cfg, venv, tmp_path / "tb")
    warm = WarmStart(rounds=1, steps_per_round=40, preset="schedule:latency")
    _, labels, delays = warm.run(model, venv)["dataset"]
    per_step = delays.reshape(40, 6)  # 40 ticks: no episode ends, each copy keeps its airframe
    assert len(delays) == len(labels) and (per_step == episode_delay_ticks(venv.unwrapped.batch)).all()
    assert len(set(per_step[0].tolist())) > 1


@pytest.mark.slow
def test_the_anchor_can_keep_to_the_airframes_with_a_long_delay(tmp_path: Path):
    import json

    from fcemu.training.train import train

    cfg = TrainConfig(algo="ppo", seed=0, out=str(tmp_path), envs=8, steps=1024, checkpoint_every=100_000,
                      eval_every=0, eval_episodes=0, warm_start="schedule:latency", warm_start_rounds=1,
                      warm_start_steps=300, randomize="iris", anchor=1.0, anchor_from_ticks=3,
                      progress=False, hp={"n_steps": 128, "batch_size": 256})
    train(cfg)
    kept = json.loads((tmp_path / "summary.json").read_text())["warm_start"]["anchor_samples"]
    assert 0 < kept < 300 * 8 and kept % 300 == 0  # whole episodes: none ends within 300 ticks


def test_anchor_from_ticks_goes_with_an_anchor():
    with pytest.raises(ValueError, match="goes with --anchor"):
        TrainConfig(warm_start="pid", anchor_from_ticks=3)
    with pytest.raises(ValueError, match="must be >= 0"):
        TrainConfig(warm_start="pid", anchor=1.0, anchor_from_ticks=-1)
    assert TrainConfig(warm_start="pid", anchor=1.0, anchor_from_ticks=3).anchor_from_ticks == 3
