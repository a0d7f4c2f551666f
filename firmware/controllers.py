"""Controllers by name: `default` (what the firmware flies where none is named), `pid` (the airframe's
tune), `pid:<preset>`, an ONNX policy, an exported C policy."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from importlib.resources import files
from pathlib import Path

from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.controller import RateController
from fcemu.firmware.errors import UserError
from fcemu.firmware.pid_controller import PRESET_DIR

# Package data, so an installed wheel flies it as a checkout does.
DEFAULT_POLICY = Path(str(files("fcemu.firmware") / "policies" / "iris_rate_ppo.onnx"))
FALLBACK_CONTROLLER = "pid"  # what flies when a policy faults, and in LAND and HOLD
DEFAULT = "default"  # `default_for` the airframe the firmware is configured with
# The longest loop (ESC + gyro delay, ticks: AirframeSpec.loop_delay_ticks) the shipped policy holds
# in flight on perturbed airframes; on a longer one its gains ring, and a PID tuned for the latency
# holds (docs/results/robustness.md, "the default by the loop's delay").
DEFAULT_POLICY_LONGEST_LOOP_TICKS = 3
LATENCY_PRESET = "pid_{}_robust.json"  # an airframe's tune for a long loop, where one ships
PROPS_OUT = "props spin out (motor 1 counter-clockwise) and a policy is made for props in"


class ControllerSpecError(UserError, ValueError):
    """A --controller that names no controller."""


def default_controller() -> str:
    """The shipped policy when it is present, else the PID."""
    return str(DEFAULT_POLICY) if DEFAULT_POLICY.exists() else FALLBACK_CONTROLLER


def default_for(airframe: AirframeSpec | None) -> str:
    """The shipped policy (`default_controller`) where it holds `airframe`; else the airframe's PID: on a
    loop longer than the policy holds, its tune for latency (`pid_<name>_robust`, where one ships). A
    flight controller knows its loop's delay: its gyro filters and ESC protocol are its configuration."""
    policy = default_controller()
    if airframe is None or policy == FALLBACK_CONTROLLER:
        return policy
    if default_refusal(airframe) is not None:
        return FALLBACK_CONTROLLER
    if airframe.loop_delay_ticks <= DEFAULT_POLICY_LONGEST_LOOP_TICKS:
        return policy
    name = airframe.tune_of or airframe.name
    latency_tune = PRESET_DIR / LATENCY_PRESET.format(name)
    return f"pid:{latency_tune.stem.removeprefix('pid_')}" if latency_tune.exists() else FALLBACK_CONTROLLER


def default_refusal(airframe: AirframeSpec) -> str | None:
    """Why the shipped policy does not fly `airframe` (outside the envelope it was made for), or None."""
    from fcemu.firmware.contract import PolicyContract, PolicyContractError
    from fcemu.firmware.neural import read_metadata

    try:
        contract = PolicyContract.from_metadata(read_metadata(DEFAULT_POLICY), str(DEFAULT_POLICY))
        contract.check_airframe(airframe, str(DEFAULT_POLICY.name))
    except PolicyContractError as exc:
        return str(exc)
    return None


def resolve(spec: str, airframe: AirframeSpec | None) -> str:
    """`spec` with `default` resolved for `airframe`; any other name as it is."""
    return default_for(airframe) if spec == DEFAULT else spec


def is_policy(spec: str) -> bool:
    """A learned policy (flown as CTRL_SEL `neural`): an ONNX file or an exported C policy directory."""
    from fcemu.firmware.c_policy import is_c_policy_dir

    return spec.endswith(".onnx") or is_c_policy_dir(spec)


def airframe_preset(airframe: AirframeSpec) -> Path:
    """`firmware/presets/pid_<name>.json` of the airframe, or of the airframe a variant of the same
    nominal physics varies (its file's `base`: iris_realistic flies pid_iris)."""
    name = airframe.tune_of or airframe.name
    path = PRESET_DIR / f"pid_{name}.json"
    if path.exists():
        return path
    raise ControllerSpecError(
        f"no PID tuned for {airframe.name}: `fcemu tune --airframe {airframe.name} --out DIR` "
        "(or `fcemu fit`), then pid:DIR/pid.json as --controller, or as --fallback under a policy")


def policy_fallback(policy: str) -> str | None:
    """`pid:FILE` of the PID an ONNX policy names as its fallback in its metadata (`fcemu fit`'s
    DIR/pid.json beside DIR/policy.onnx), or None; a named file that is missing is refused."""
    if not policy.endswith(".onnx") or not Path(policy).is_file():
        return None
    from fcemu.firmware.contract import named_fallback
    from fcemu.firmware.neural import read_metadata

    try:
        meta = read_metadata(policy)
    except Exception:  # onnxruntime raises several unrelated types for a bad file; loading it says which
        return None
    path = named_fallback(meta, policy)
    if path is None:
        return None
    if not path.is_file():
        raise ControllerSpecError(f"policy {policy} names its fallback PID {path}, which is missing: "
                                  "name one with --fallback pid:FILE")
    return f"pid:{path}"


def resolve_fallback(fallback: str | None, controllers: Sequence[str],
                     airframe: Callable[[], AirframeSpec]) -> str:
    """The PID a policy among `controllers` hands over to (and CTRL_SEL's pid): `fallback` where given;
    else the one PID file the policies name (`policy_fallback`); else `pid`, the airframe's own tune,
    but where none ships (`airframe()`, asked only then), the one pid:FILE flown beside the policy."""
    if fallback is None:
        named = {f for f in map(policy_fallback, controllers) if f is not None}
        if len(named) == 1:
            return named.pop()
        fallback = FALLBACK_CONTROLLER
    presets = [c for c in controllers if c.startswith("pid:")]
    if fallback != FALLBACK_CONTROLLER or len(presets) != 1:
        return fallback
    try:
        airframe_preset(airframe())
    except ControllerSpecError:
        return presets[0]
    return fallback


def load_controller(spec: str, loop_rate_hz: float | None = None,
                    airframe: AirframeSpec | None = None) -> RateController:
    """`loop_rate_hz`: the rate the loop will run it at; a policy trained for another rate is refused.
    `airframe`: the one it will fly: `pid` is that airframe's tune, and a policy whose envelope does
    not hold it is refused. Without one nothing is checked and `pid` is the default preset."""
    spec = resolve(spec, airframe)
    if spec == "pid" or spec.startswith("pid:"):
        from fcemu.firmware.pid_controller import DEFAULT_PRESET, PIDRateController

        preset = spec.partition(":")[2]
        if not preset:
            preset = DEFAULT_PRESET if airframe is None else str(airframe_preset(airframe))
        try:
            controller = PIDRateController.from_preset(preset)
        except (ValueError, KeyError, TypeError) as exc:  # an unknown preset or a preset file that is not one
            raise ControllerSpecError(f"controller {spec!r}: {exc}") from exc
        if airframe is not None and airframe.props_out and not controller.mixer.yaw_reversed:
            controller.mixer = _yaw_reversed(controller.mixer)
        return controller
    if airframe is not None and airframe.props_out:
        raise ControllerSpecError(f"controller {spec!r}: {airframe.name}'s {PROPS_OUT}: fly the PID")
    if spec.endswith(".onnx"):
        from fcemu.firmware.neural import NeuralRateController

        return NeuralRateController(spec, loop_rate_hz=loop_rate_hz, airframe=airframe)
    from fcemu.firmware.c_policy import CPolicyController, is_c_policy_dir

    if is_c_policy_dir(spec):  # a directory written by `fcemu export --target c`
        return CPolicyController(spec, loop_rate_hz=loop_rate_hz, airframe=airframe)
    raise ControllerSpecError(f"unknown controller {spec!r}: use pid, pid:<preset>, a .onnx file "
                              "or a directory from `fcemu export --target c`")


def _yaw_reversed(mixer):
    """The same mixer for props spinning out, as Betaflight's yaw_motors_reversed flies them."""
    from fcemu.firmware.mixer import QuadXMixer

    table = mixer.table_name if mixer.table_name != "custom" else mixer.table
    return QuadXMixer(table, mixer.idle, mixer.airmode, mixer.pwm_min, mixer.pwm_max, yaw_reversed=True)
