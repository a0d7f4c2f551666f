"""`fcemu distill`: the observation both policies read, and a short run end to end."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

from fcemu.export.onnx_export import export_policy
from fcemu.firmware.neural import NeuralRateController
from fcemu.firmware.observation import (
    INTEGRAL,
    MOTOR_OUTPUT,
    RMS,
    ObservationHistory,
    ObservationSpec,
    observe_step,
)
from fcemu.sim_bridge.airframe import AIRFRAME_DIR, DEFAULT_AIRFRAME, load_airframe
from fcemu.sim_bridge.randomization import parse_randomization
from fcemu.sim_bridge.vec_env import BatchedRateEnv
from fcemu.training.distill import (
    INVERSION,
    DistillConfig,
    DistillError,
    Teacher,
    columns,
    distill,
    fly,
    imitation_mse,
    make_teacher,
    nudge,
    student_train_config,
    union_spec,
)

pytestmark = pytest.mark.no_wall_clock

TEACHER = Path(__file__).parents[2] / "policies" / "iris_rate_ppo_rms64_mo.onnx"


def _spec(**kwargs) -> ObservationSpec:
    """An observation spec scaled for the default airframe's top rotor speed."""
    return ObservationSpec(max_rotor_speed=load_airframe(DEFAULT_AIRFRAME).motor.max_rotor_speed, **kwargs)


def _history(spec: ObservationSpec, steps: list[tuple[np.ndarray, ...]]) -> np.ndarray:
    """The firmware's observation after these (setpoint, gyro, rotor, previous u) steps."""
    history = ObservationHistory(spec)
    setpoint, gyro, rotor, u = steps[0]
    history.start(observe_step(spec, setpoint, gyro, rotor, motor_output=u))
    for setpoint, gyro, rotor, u in steps[1:]:
        history.record(observe_step(spec, setpoint, gyro, rotor, motor_output=u))
    return history.observation()


@pytest.mark.parametrize("student", [
    _spec(memory=2, fields=("rate_error", "rotor_speed", INTEGRAL, RMS, MOTOR_OUTPUT)),
    _spec(memory=1, fields=("rate_error", "rotor_speed", RMS)),
    _spec(memory=5, fields=("rate_error", "rotor_speed", MOTOR_OUTPUT, INTEGRAL)),
])
def test_each_policy_reads_from_the_union_what_the_firmware_builds_for_it(student):
    teacher = _spec(memory=3, fields=("rate_error", "rotor_speed", INTEGRAL, RMS))
    union = union_spec(teacher, student)
    rng = np.random.default_rng(0)
    steps = [(rng.uniform(-5, 5, 3), rng.uniform(-5, 5, 3), rng.uniform(0, 1100, 4), rng.uniform(0, 1, 4))
             for _ in range(7)]
    flown = _history(union, steps)
    for spec in (teacher, student):
        np.testing.assert_array_equal(flown[columns(spec, union)], _history(spec, steps))


def test_by_default_the_student_reads_the_teachers_whole_history_and_a_bad_memory_is_refused(tmp_path):
    teacher = Teacher(TEACHER)
    _, spec = student_train_config(DistillConfig(teacher=str(TEACHER)), teacher)
    assert spec.memory == teacher.spec.memory == 16 and spec.fields == teacher.spec.fields
    with pytest.raises(DistillError, match="--memory"):
        distill(DistillConfig(teacher=str(TEACHER), out=str(tmp_path / "s"), memory=0))


def test_a_student_with_other_leaks_than_the_teacher_is_refused():
    with pytest.raises(DistillError, match="rms_leak"):
        union_spec(_spec(fields=("rate_error", "rotor_speed", RMS)),
                   _spec(fields=("rate_error", "rotor_speed", RMS), rms_leak=0.9))


def test_a_nudge_moves_only_the_students_columns_and_the_teacher_labels_the_moved_state():
    teacher = Teacher(TEACHER)
    student = _spec(memory=2, fields=("rate_error", "rotor_speed", INTEGRAL, RMS, MOTOR_OUTPUT),
                              integral_leak=teacher.spec.integral_leak, rms_leak=teacher.spec.rms_leak)
    union = union_spec(teacher.spec, student)
    cols = (columns(teacher.spec, union), columns(student, union))
    rng = np.random.default_rng(0)
    flown = rng.normal(size=(3, 5, union.size)).astype(np.float32)  # (steps, twins, observation)
    std = rng.uniform(0.5, 2.0, student.size)
    moved, labels = nudge(flown, teacher, cols, std, 0.05, np.random.default_rng(1))
    flat = flown.reshape(15, -1)
    step = (moved - flat[:, cols[1]]) / std
    assert 0.03 < step.std() < 0.07 and moved.shape == (15, student.size)
    hidden = np.setdiff1d(cols[0], cols[1])  # the teacher's older steps, which the student never sees
    assert len(hidden) == teacher.spec.size - student.size
    again = flat.copy()
    again[:, cols[1]] = moved
    np.testing.assert_allclose(labels, teacher.act(np.ascontiguousarray(again[:, cols[0]])), atol=1e-6)


    # privileged: the teacher read `flown`, the student `seen`; both moved the same way
    seen = flown + 0.5
    moved_seen, labels_seen = nudge(flown, teacher, cols, std, 0.05, np.random.default_rng(1), seen)
    np.testing.assert_allclose(moved_seen - seen.reshape(15, -1)[:, cols[1]], moved - flat[:, cols[1]],
                               atol=1e-6)
    np.testing.assert_array_equal(labels_seen, labels)


def test_on_a_late_telemetry_bus_the_teacher_labels_what_it_would_do_on_time():
    teacher = Teacher(TEACHER)
    late = parse_randomization({"airframe": "iris", "parameters": {"esc_telemetry_delay_ticks": {
        "nominal": 0, "range": [3, 3], "unit": "ticks", "source": "test"}}})
    env = BatchedRateEnv(3, on_time_view=True, randomize=late, memory=teacher.spec.memory,
                         obs_fields=teacher.spec.fields, action_mapping="throttle", throttle=0.6,
                         episode_s=0.1, reward="unclipped",
                         integral_leak=teacher.spec.integral_leak, rms_leak=teacher.spec.rms_leak)
    cols = (np.arange(teacher.spec.size),) * 2
    obs, _ = env.reset(seed=3)
    s_obs, labels, _, _, _, (on_time, seen) = fly(env, teacher, None, cols, 30, 1.0, np.random.default_rng(0),
                                                  obs, None, keep_union=True, privileged=True)
    np.testing.assert_array_equal(s_obs, seen)  # the student's own, late view
    assert not np.array_equal(on_time, seen)
    np.testing.assert_allclose(labels, [teacher.act(np.ascontiguousarray(o)) for o in on_time], atol=1e-6)
    obs, _ = env.reset(seed=3)  # not privileged: the teacher reads what the student reads
    s_obs, labels, _, _, _, (_, seen) = fly(env, teacher, None, cols, 30, 1.0, np.random.default_rng(0),
                                                obs, None, keep_union=True)
    assert seen is None
    np.testing.assert_allclose(labels, [teacher.act(np.ascontiguousarray(o)) for o in s_obs], atol=1e-6)


def test_the_gain_match_fits_the_teachers_slopes(tmp_path):
    """A student fitted with the gain match responds to a nudge more like the teacher than one fitted
    with it at a negligible weight (which still measures it)."""
    runs = {}
    for weight in (1e-9, 1.0):
        out = tmp_path / f"g{weight}"
        distill(DistillConfig(teacher=str(TEACHER), out=str(out), memory=2, net_arch=(16, 16), rounds=2,
                              steps=100, envs=4, fit_steps=300, batch_size=256, gain_weight=weight,
                              threads=1, progress=False))
        runs[weight] = json.loads((out / "summary.json").read_text())["history"][-1]
    assert runs[1.0]["gain_mse"] < 0.7 * runs[1e-9]["gain_mse"]


def test_a_short_distillation_leaves_a_run_that_exports_and_flies(tmp_path):
    out = tmp_path / "student"
    summary = distill(DistillConfig(teacher=str(TEACHER), out=str(out), memory=1, net_arch=(16, 16),
                                    rounds=2, steps=60, envs=4, fit_steps=20, batch_size=256,
                                    smoothness=0.1, threads=1, progress=False))
    assert [h["teacher_share"] for h in summary["history"]] == [1.0, 0.5]
    assert summary["history"][-1]["imitation_mse"] < summary["history"][0]["imitation_mse"] * 2
    config = json.loads((out / "config.json").read_text())
    assert config["observation"]["memory"] == 1 and config["trained_steps"] == 2 * 60 * 4
    assert config["distill"]["teacher"] == str(TEACHER)
    # the ONNX carries the firmware's contract, and `fcemu export` of the run gives the same graph
    controller = NeuralRateController(out / "policy.onnx")
    assert controller.spec.size == 17 and controller.spec.fields[-1] == MOTOR_OUTPUT
    again = export_policy(out, tmp_path / "again.onnx")
    assert again["parity_ok"]
    obs = np.random.default_rng(1).normal(size=(32, 17)).astype(np.float32)
    a, b = (ort.InferenceSession(str(p)).run(None, {"observation": obs})[0]
            for p in (out / "policy.onnx", tmp_path / "again.onnx"))
    np.testing.assert_array_equal(a, b)


def test_the_command_refuses_a_teacher_that_is_not_a_policy(tmp_path):
    bogus = tmp_path / "teacher.onnx"
    bogus.write_bytes(b"not a model")
    proc = subprocess.run([sys.executable, "-m", "fcemu", "distill", str(bogus), "--out", str(tmp_path / "o"),
                           "--no-progress"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.startswith("fcemu: error: ") and proc.stderr.count("\n") == 1


def test_a_teacher_made_for_another_airframe_is_refused_unless_chosen(tmp_path):
    raw = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    raw.update(name="iris_heavy", base_mass_kg=1.7)
    path = tmp_path / "iris_heavy.json"
    path.write_text(json.dumps(raw))
    teacher = Teacher(TEACHER)
    assert teacher.airframe == "iris"
    cfg = DistillConfig(teacher=str(TEACHER), airframe=str(path), randomize="none", threads=1)
    with pytest.raises(DistillError, match="made for airframe 'iris', not 'iris_heavy'"):
        student_train_config(cfg, teacher)
    train_cfg, _ = student_train_config(dataclasses.replace(cfg, foreign_teacher=True), teacher)
    assert train_cfg.env_config().base_airframe.name == "iris_heavy" and train_cfg.randomize is None
    proc = subprocess.run([sys.executable, "-m", "fcemu", "distill", str(TEACHER), "--airframe", str(path),
                           "--randomize", "none", "--out", str(tmp_path / "o"), "--no-progress"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "--foreign-teacher" in proc.stderr


def test_the_student_flies_the_airframes_training_ranges_by_default():
    train_cfg, _ = student_train_config(DistillConfig(teacher=str(TEACHER), threads=1), Teacher(TEACHER))
    assert (train_cfg.randomize, train_cfg.randomize_share) == ("iris_esc2", 0.5)


def test_a_student_for_another_airframe_flies_its_relative_ranges_and_carries_its_airframe(tmp_path):
    from fcemu.training.config import TrainConfig
    from fcemu.training.train import train

    run = tmp_path / "crazyflie"
    train(TrainConfig(airframe="crazyflie", steps=128, envs=2, seed=1, out=str(run), eval_episodes=0,
                      checkpoint_every=10**9, hp={"n_steps": 64, "batch_size": 64}, threads=1,
                      progress=False))
    out = tmp_path / "student"
    distill(DistillConfig(teacher=str(run / "policy.onnx"), airframe="crazyflie", out=str(out), rounds=1,
                          steps=20, envs=2, fit_steps=5, batch_size=64, threads=1, progress=False))
    config = json.loads((out / "config.json").read_text())
    assert (config["airframe"], config["randomize"]) == ("crazyflie", "relative") == \
        (config["env"]["airframe"], config["env"]["randomize"])
    meta = ort.InferenceSession(str(out / "policy.onnx")).get_modelmeta().custom_metadata_map
    assert meta["fcemu.airframe"] == "crazyflie"


def test_past_a_saturated_label_the_mixer_clips_so_the_fit_sees_no_error():
    import torch

    from fcemu.firmware.action import throttle_pwm

    label = torch.tensor([[1.0, -1.0, 0.5, -0.5]])
    past = torch.tensor([[1.4, -1.3, 0.5, -0.5]])  # beyond the two saturated motors only
    assert float(imitation_mse(past, label)) == 0.0
    assert np.array_equal(throttle_pwm(past.numpy(), 0.5), throttle_pwm(label.numpy(), 0.5))
    short = torch.tensor([[0.9, -1.0, 0.5, -0.5]])  # short of a saturated label is an error
    inside = torch.tensor([[1.0, -1.0, 0.9, -0.5]])  # and so is any miss of an unsaturated one
    beyond = torch.tensor([[1.0, -1.0, 0.5, -1.2]])
    assert all(float(imitation_mse(p, label)) > 0.0 for p in (short, inside, beyond))


def test_a_teacher_per_twin_labels_each_twin_as_the_teacher_of_its_drawn_airframe_would():
    """Each row is labelled by the inversion teacher built for that twin's airframe as drawn this episode
    (its delays, motors, damping), and the rows follow the twins as their episodes end and draw anew."""
    ranges = parse_randomization({"airframe": "iris", "parameters": {
        "esc_delay_ticks": {"nominal": 0, "range": [0, 3], "unit": "ticks", "source": "test"},
        "tau_up": {"nominal": 0.0125, "range": [0.008, 0.03], "unit": "s", "source": "test"}}})
    teacher = make_teacher(INVERSION, "iris", privileged=True, per_twin=True)
    env = BatchedRateEnv(4, on_time_view=True, truth_view=True, randomize=ranges, randomize_share=1.0,
                         memory=1, obs_fields=teacher.spec.fields, action_mapping="throttle",
                         episode_s=0.02, integral_leak=teacher.spec.integral_leak,
                         rms_leak=teacher.spec.rms_leak)
    teacher.follow(env)
    obs, _ = env.reset(seed=5)
    own = {}
    for _ in range(3 * 20):  # three episodes of every twin
        labels = teacher.act(obs)
        for i, factors in enumerate(env.episode_factors):
            key = tuple(sorted(factors.items()))
            if key not in own:
                own[key] = make_teacher(INVERSION, load_airframe("iris").scaled(**factors), privileged=True)
            np.testing.assert_allclose(labels[i], own[key].act(obs[i:i + 1])[0], atol=1e-9)
        obs, *_ = env.step(labels.astype(np.float32))
    drawn = set(own)
    assert len(drawn) == 12 and {dict(k)["esc_delay_ticks"] for k in drawn} > {0}


def test_a_teacher_per_twin_is_the_model_based_ones_and_teaches_without_the_gain_match(tmp_path):
    with pytest.raises(DistillError, match="model-based"):
        make_teacher(str(TEACHER), "iris", per_twin=True)
    with pytest.raises(DistillError, match="gain-weight 0"):
        distill(DistillConfig(teacher=INVERSION, out=str(tmp_path / "o"), per_twin=True, gain_weight=0.1,
                              threads=1, progress=False))


def test_on_a_pool_of_quads_each_twin_is_labelled_by_its_own_quads_teacher():
    """The twins observe rotor speeds as shares of their own top speeds; each row's label is what the
    teacher built for that quad would give on the observation its own firmware builds."""
    from fcemu.sim_bridge.airframe_draw import airframe_pool

    pool = airframe_pool("draw:4:3")
    teacher = make_teacher(INVERSION, "iris", privileged=True, per_twin=True)
    env = BatchedRateEnv(4, on_time_view=True, truth_view=True, airframe_pool=pool, memory=1,
                         obs_fields=teacher.spec.fields, action_mapping="throttle", episode_s=0.02)
    teacher.follow(env)
    env.reset(seed=2)
    own = {a.name: make_teacher(INVERSION, a, privileged=True) for a in pool}
    seen = set()
    for _ in range(3 * 20):
        truth = env.on_time_observation
        labels = teacher.act(truth)
        for i, quad in enumerate(env.episode_airframes):
            single = own[quad.name]  # its own firmware's scale is 1 / its top speed: the same shares
            assert single.spec.rotor_speed_scale == 1.0 / quad.motor.max_rotor_speed
            np.testing.assert_allclose(labels[i], single.act(truth[i:i + 1])[0], atol=1e-6)
            seen.add(quad.name)
        env.step(labels.astype(np.float32))
    assert len(seen) >= 3


def test_a_student_of_a_pool_flies_each_quad_on_its_own_top_speed_and_not_in_betaflight(tmp_path):
    from fcemu.export.betaflight.build import BetaflightExportError, check_contract
    from fcemu.sim_bridge.airframe_draw import airframe_pool
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    out = tmp_path / "shared"
    distill(DistillConfig(teacher=INVERSION, out=str(out), airframe_pool="draw:6:4", memory=2,
                          net_arch=(16, 16), rounds=2, steps=40, envs=6, fit_steps=20, batch_size=256,
                          threads=1, progress=False))
    policy = out / "policy.onnx"
    for quad in airframe_pool("draw:6:4")[:2]:
        controller = NeuralRateController(policy, airframe=airframe_spec(quad))
        assert controller.spec.per_airframe_rotor_speed
        assert controller.spec.rotor_speed_scale == 1.0 / quad.motor.max_rotor_speed
    assert "the pool draw:6:4" in NeuralRateController(policy).contract.airframe
    with pytest.raises(BetaflightExportError, match="shares of the flown airframe's top speed"):
        check_contract(policy)
