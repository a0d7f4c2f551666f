"""Every contract field is checked at load: models built from the shipped policy with lying metadata."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from fcemu.firmware.contract import META_PREFIX, PolicyContract, PolicyContractError
from fcemu.firmware.controllers import DEFAULT_POLICY, load_controller
from fcemu.firmware.neural import NeuralRateController
from fcemu.firmware.observation import ObservationSpec

SHIPPED = {p.key[len(META_PREFIX):]: p.value
           for p in onnx.load(str(DEFAULT_POLICY), load_external_data=False).metadata_props}
SPEC = json.loads(SHIPPED["observation"])


def lying_copy(path: Path, changes: dict[str, str | None], scale_outputs: float | None = None) -> Path:
    """The shipped policy with its metadata rewritten (None removes a key), optionally its output scaled."""
    model = onnx.load(str(DEFAULT_POLICY))
    meta = {**SHIPPED, **changes}
    del model.metadata_props[:]
    for k, v in meta.items():
        if v is not None:
            model.metadata_props.add(key=META_PREFIX + k, value=v)
    if scale_outputs is not None:
        out = model.graph.output[0].name
        for node in model.graph.node:
            node.output[:] = [f"{o}_raw" if o == out else o for o in node.output]
        model.graph.initializer.append(numpy_helper.from_array(np.float32([scale_outputs]), "scale"))
        model.graph.node.append(helper.make_node("Mul", [f"{out}_raw", "scale"], [out]))
    onnx.save(model, str(path))
    return path


def obs(**changes: object) -> str:
    return json.dumps({**SPEC, **changes})


LIES = {
    "loop_rate_nan": ({"loop_rate_hz": "nan"}, "loop_rate_hz 'nan'"),
    "loop_rate_inf": ({"loop_rate_hz": "inf"}, "loop_rate_hz"),
    "loop_rate_500": ({"loop_rate_hz": "500.0"}, "trained for a 500 Hz loop, asked to run at 1000 Hz"),
    "loop_rate_text": ({"loop_rate_hz": "fast"}, "not a number"),
    "loop_rate_negative": ({"loop_rate_hz": "-1000"}, "loop_rate_hz"),
    "throttle_reversed": ({"throttle": "[0.9, 0.1]"}, "throttle"),
    "throttle_nan": ({"throttle": "[NaN, 2]"}, "throttle"),
    "throttle_text": ({"throttle": "abc"}, "throttle 'abc'"),
    "throttle_above_one": ({"throttle": "1.5"}, "throttle"),
    "throttle_bool": ({"throttle": "true"}, "throttle"),
    "throttle_three": ({"throttle": "[0.1, 0.2, 0.3]"}, "throttle"),
    "swapped_scales": ({"observation": obs(rate_scale=SPEC["rotor_speed_scale"],
                                           rotor_speed_scale=SPEC["rate_scale"])}, "rate_scale"),
    "swapped_mapping_and_rate": ({"action_mapping": "1000.0", "loop_rate_hz": "throttle"}, "action mapping"),
    "rate_scale_huge_negative": ({"observation": obs(rate_scale=-1e30)}, "rate_scale"),
    "rate_scale_nan": ({"observation": obs(rate_scale=float("nan"))}, "rate_scale"),
    "rate_scale_text": ({"observation": obs(rate_scale="1")}, "rate_scale"),
    "rotor_scale_zero": ({"observation": obs(rotor_speed_scale=0)}, "rotor_speed_scale"),
    "memory_float": ({"observation": obs(memory=1.5)}, "memory"),
    "memory_bool": ({"observation": obs(memory=True)}, "memory"),
    "memory_huge": ({"observation": obs(memory=10**9)}, "memory"),
    "memory_vs_graph": ({"observation": obs(memory=SPEC["memory"] + 1)}, "input shape"),
    "fields_swapped_sizes": ({"observation": obs(fields=["rate_error", "rate_error_integral"])},
                             "input shape"),
    "fields_not_a_list": ({"observation": obs(fields="rate_error")}, "fields"),
    "unknown_spec_key": ({"observation": obs(attitude=1)}, "not understood"),
    "spec_deeply_nested": ({"observation": "[" * 100_000 + "]" * 100_000}, "not understood"),
    "spec_not_object": ({"observation": "[1, 2]"}, "not understood"),
    "version_text": ({"observation": obs(version="1")}, "version"),
    "leak_one": ({"observation": obs(integral_leak=1.0)}, "integral_leak"),
    "rms_leak_nan": ({"observation": obs(rms_leak=float("nan"))}, "rms_leak"),
    "no_mapping": ({"action_mapping": None}, "metadata lacks"),
    "envelope_text": ({"envelope": "wide"}, "envelope not understood"),
    "envelope_reversed": ({"envelope": '{"max_rotor_speed": [1200, 1100]}'}, "envelope not understood"),
    "rotor_scale_for_another_top_speed": ({"envelope": '{"max_rotor_speed": [26000, 26000]}'},
                                          "rotor_speed_scale"),
    "no_rotor_scale": ({"observation": json.dumps({k: v for k, v in SPEC.items()
                                                   if k != "rotor_speed_scale"})}, "lacks rotor_speed_scale"),
}


@pytest.mark.parametrize("name", sorted(LIES))
def test_lying_metadata_is_refused_with_one_line(tmp_path: Path, name: str) -> None:
    changes, message = LIES[name]
    path = lying_copy(tmp_path / f"{name}.onnx", changes)
    with pytest.raises(PolicyContractError, match=message.replace("[", r"\[")) as info:
        NeuralRateController(path, loop_rate_hz=1000.0)
    assert "\n" not in str(info.value) and len(str(info.value)) < 400


def test_outputs_far_outside_the_action_space_are_refused(tmp_path: Path) -> None:
    with pytest.raises(PolicyContractError, match="outputs up to"):
        NeuralRateController(lying_copy(tmp_path / "big.onnx", {}, scale_outputs=1e30))
    NeuralRateController(lying_copy(tmp_path / "x2.onnx", {}, scale_outputs=2.0))  # clipped, as in training


def test_the_loop_rate_reaches_the_check_from_every_loader(tmp_path: Path) -> None:
    from fcemu.evaluation.runner import run_controller  # noqa: F401  (imports load_controller with the rate)
    from fcemu.sitl.sitl import build_sitl

    with pytest.raises(PolicyContractError, match="asked to run at 500 Hz"):
        load_controller(str(DEFAULT_POLICY), 500.0)
    with pytest.raises(PolicyContractError, match="asked to run at 500 Hz"):
        build_sitl(str(DEFAULT_POLICY), rig="rig", rate_hz=500.0, realtime=False)
    sitl = build_sitl(str(DEFAULT_POLICY), rig="rig", rate_hz=1000.0, realtime=False)
    assert sitl.selected == "neural"


def test_the_shipped_contract_round_trips() -> None:
    contract = PolicyContract.from_metadata(SHIPPED, "shipped", 1000.0)
    assert contract.observation == ObservationSpec.from_json(SHIPPED["observation"])
    assert contract.throttle == (0.5, 0.9) and contract.action_mapping == "throttle"
    assert PolicyContract.from_metadata({**SHIPPED, "throttle": "null"}).throttle is None
    without = {k: v for k, v in SHIPPED.items() if k != "throttle"}
    assert PolicyContract.from_metadata(without).throttle is None


def _airframe(name: str, **scaled: float):
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    return airframe_spec(load_airframe(name).scaled(**scaled))


def test_a_policy_flies_only_airframes_inside_its_envelope() -> None:
    assert SHIPPED["airframe"] == "iris"
    NeuralRateController(DEFAULT_POLICY, airframe=_airframe("iris"))
    NeuralRateController(DEFAULT_POLICY, airframe=_airframe("iris", mass=1.1, kf=0.95, tau_up=1.15))
    with pytest.raises(PolicyContractError) as info:
        load_controller(str(DEFAULT_POLICY), 1000.0, _airframe("crazyflie"))
    message = str(info.value)
    assert message.startswith(f"policy {DEFAULT_POLICY} was made for iris (thrust-to-weight 1.41–2.33, "
                              "top rotor speed 1,100 rad/s); crazyflie's top rotor speed 2,274 rad/s")
    assert message.endswith("outside it") and "\n" not in message
    with pytest.raises(PolicyContractError, match=r"; iris's thrust-to-weight 1\.2, hover throttle 0\.913, "):
        NeuralRateController(DEFAULT_POLICY, airframe=_airframe("iris", mass=1.5))


def test_a_policy_without_an_envelope_flies_an_airframe_of_its_top_rotor_speed(tmp_path: Path) -> None:
    legacy = lying_copy(tmp_path / "legacy.onnx", {"envelope": None, "airframe": None})
    NeuralRateController(legacy, airframe=_airframe("iris", mass=1.5))  # only the top speed is known
    with pytest.raises(PolicyContractError, match="records no envelope and was made for a top rotor speed of "
                                                  "1,100 rad/s; x500's is"):
        NeuralRateController(legacy, airframe=_airframe("x500"))


def test_rotor_speeds_as_shares_of_the_flown_airframes_top_speed_take_its_scale(tmp_path: Path) -> None:
    shares = lying_copy(tmp_path / "shares.onnx", {"envelope": None, "airframe": None,
                                                    "observation": obs(per_airframe_rotor_speed=True)})
    x500 = _airframe("x500")  # another top speed than the policy's airframe: no longer refused
    controller = NeuralRateController(shares, airframe=x500)
    assert controller.spec.rotor_speed_scale == 1.0 / x500.max_rotor_speed
    assert NeuralRateController(shares).spec.rotor_speed_scale == SPEC["rotor_speed_scale"]  # none given
    assert json.loads(controller.contract.observation.to_json())["per_airframe_rotor_speed"] is True
    assert "per_airframe_rotor_speed" not in json.loads(NeuralRateController(DEFAULT_POLICY).spec.to_json())
    with pytest.raises(PolicyContractError, match="per_airframe_rotor_speed 'yes' is not true or false"):
        NeuralRateController(lying_copy(tmp_path / "bad.onnx",
                                        {"observation": obs(per_airframe_rotor_speed="yes")}))


def test_pid_is_the_airframe_s_own_tune(untuned_airframe: Path) -> None:
    from fcemu.firmware.controllers import ControllerSpecError

    assert load_controller("pid", airframe=_airframe("iris")).name == "pid_iris"
    assert load_controller("pid", airframe=_airframe("iris_realistic")).name == "pid_iris"  # its base's
    assert load_controller("pid", airframe=_airframe("crazyflie")).name == "pid_crazyflie"
    refusal = (r"^no PID tuned for my_quad: `fcemu tune --airframe my_quad --out DIR` "
               r"\(or `fcemu fit`\), then pid:DIR/pid\.json as --controller, or as --fallback under a "
               r"policy$")
    with pytest.raises(ControllerSpecError, match=refusal):
        load_controller("pid", airframe=_airframe(str(untuned_airframe)))
    for named in ("pid:iris", "pid:paper"):
        load_controller(named, airframe=_airframe(str(untuned_airframe)))


def test_a_variant_flies_its_bases_tune_only_when_it_changes_no_physics(tmp_path) -> None:
    from fcemu.firmware.controllers import ControllerSpecError
    from fcemu.sim_bridge.airframe import AIRFRAME_DIR, load_airframe
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    base = json.loads((AIRFRAME_DIR / "racer5.json").read_text())
    noisy = tmp_path / "racer5_noisy.json"
    noisy.write_text(json.dumps({"name": "racer5_noisy", "base": str(AIRFRAME_DIR / "racer5.json"),
                                 "effects": {"gyro_noise_std_rad_s": {"value": 0.01, "source": "test"}}}))
    assert load_controller("pid", airframe=airframe_spec(load_airframe(noisy))).name == "pid_racer5"
    heavy = tmp_path / "racer5_heavy.json"
    heavy.write_text(json.dumps({"name": "racer5_heavy", "base": str(AIRFRAME_DIR / "racer5.json"),
                                 "base_mass_kg": base["base_mass_kg"] * 1.5}))
    with pytest.raises(ControllerSpecError, match=r"^no PID tuned for racer5_heavy"):
        load_controller("pid", airframe=airframe_spec(load_airframe(heavy)))
