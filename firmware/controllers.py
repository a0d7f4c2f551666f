"""Controllers by name: `pid` (the Iris tune), `pid:<preset>`, or a path to an ONNX policy."""

from __future__ import annotations

from pathlib import Path

from firmware.controller import RateController

DEFAULT_POLICY = Path(__file__).resolve().parent.parent / "policies" / "iris_rate_ppo.onnx"


def default_controller() -> str:
    """The shipped policy when it is present, else the PID."""
    return str(DEFAULT_POLICY) if DEFAULT_POLICY.exists() else "pid"


def load_controller(spec: str) -> RateController:
    if spec == "pid" or spec.startswith("pid:"):
        from firmware.pid_controller import PIDRateController

        return PIDRateController.from_preset(spec.partition(":")[2] or "iris")
    if spec.endswith(".onnx"):
        from firmware.neural import NeuralRateController

        return NeuralRateController(spec)
    from firmware.c_policy import CPolicyController, is_c_policy_dir

    if is_c_policy_dir(spec):  # a directory written by `fcemu export --target c`
        return CPolicyController(spec)
    raise ValueError(f"unknown controller {spec!r}: use pid, pid:<preset> or a .onnx file")
