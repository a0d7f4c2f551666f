"""`fcemu train` and `fcemu distill` hold the environment's options from its one declaration (`EnvConfig`)."""

from __future__ import annotations

import dataclasses

import pytest

from fcemu.cli import build_parser
from fcemu.sim_bridge.env_config import ENV_FIELDS, EXCLUDED, command_options
from fcemu.training.config import TRAIN_RECIPE, TrainConfig, from_args
from fcemu.training.distill_config import DISTILL_EXCLUDED, DISTILL_RECIPE, DistillConfig, training_ranges

# What a command builds from its own flags instead of taking the field as it is.
DERIVED = {"obs_fields": {"train": {"--integral", "--error-rms", "--motor-output"}, "distill": {"--fields"}}}


def _flags(command: str) -> set[str]:
    sub = build_parser()._subparsers._group_actions[0].choices[command]
    return {opt for action in sub._actions for opt in action.option_strings}


@pytest.mark.parametrize("command, excluded", [("train", {}), ("distill", DISTILL_EXCLUDED)])
def test_every_env_field_is_reachable_from_the_train_and_distill_command_lines(command, excluded):
    flags = _flags(command)
    for name, f in ENV_FIELDS.items():
        if name in DERIVED:
            assert DERIVED[name][command] <= flags, (command, name)
        elif name in EXCLUDED or name in excluded:
            assert (EXCLUDED | dict(excluded))[name], (command, name)  # left out, with its reason
        else:
            flag = "--" + f.metadata.get("name", name).replace("_", "-")
            assert flag in flags, (command, name)


def test_train_and_distill_hold_the_env_options_as_fields_from_the_one_declaration():
    configs = ((TrainConfig, TRAIN_RECIPE, {}), (DistillConfig, DISTILL_RECIPE, DISTILL_EXCLUDED))
    for cls, recipe, excluded in configs:
        options = command_options(recipe, excluded)
        assert set(cls.env_options) == set(options)
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for name, option in options.items():
            assert fields[name].default == option.default
            assert fields[name].metadata["help"].startswith(ENV_FIELDS[option.field].metadata["help"])
    # the recipes are the only departures from the environment's defaults
    train = TrainConfig()
    for name, option in TrainConfig.env_options.items():
        expected = TRAIN_RECIPE.get(option.field, ENV_FIELDS[option.field].default)
        assert getattr(train, name) == expected, name
    assert TRAIN_RECIPE == {"throttle": (0.5, 0.9), "reward": "unclipped"}


def test_a_new_env_flag_reaches_the_environment_from_train_and_distill():
    args = build_parser().parse_args(["train", "--episode-s", "0.5", "--omega-max", "3.0", "--task",
                                      "continuous", "--hold-s", "0.2", "0.4"])
    env = from_args(args).env_config()
    assert (env.episode_s, env.omega_max, env.hold_s, env.n_steps) == (0.5, 3.0, (0.2, 0.4), 500)
    assert "episode_s" not in TrainConfig().env_kwargs()  # an option at its default is not written
    args = build_parser().parse_args(["distill", "teacher.onnx", "--episode-s", "0.5",
                                      "--airframe", "crazyflie"])
    assert (args.episode_s, args.airframe, args.randomize) == (0.5, "crazyflie", "own")




def test_distillations_default_ranges_are_the_airframes():
    assert training_ranges("iris") == "iris_esc2"  # the shipped default's recipe
    assert DistillConfig(teacher="t.onnx").ranges() == "iris_esc2"
    assert not DistillConfig(teacher="t.onnx").privileged  # the shipped default's recipe
    assert DistillConfig(teacher="t.onnx", randomize="none").ranges() is None
    assert DistillConfig(teacher="t.onnx", randomize="iris").ranges() == "iris"
    assert DistillConfig(teacher="t.onnx", airframe="crazyflie").ranges() == "relative"  # built for it
