"""`fcemu export --target betaflight`: refusals, the patch, and the STM32 images with their size."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from dataclasses import fields

import onnx
import pytest

from fcemu.cli import main
from fcemu.export.betaflight.build import (
    CHIPS,
    PATCH,
    BetaflightExportError,
    apply_patch,
    betaflight_source,
    check_contract,
    health_header,
    motor_model_of,
    motors_of,
    readme,
)
from fcemu.firmware.health import HealthRules
from fcemu.sim_bridge.airframe_spec import airframe_spec
from tests.export import stm32_build
from tests.export.mcu_tools import SHIPPED, _missing, require_codegen

pytestmark = pytest.mark.no_wall_clock

try:
    betaflight_source()
except BetaflightExportError as exc:
    pytest.skip(f"Betaflight source unavailable: {exc}", allow_module_level=True)


def _with_metadata(tmp_path, **changes: str):
    model = onnx.load(str(SHIPPED))
    for prop in model.metadata_props:
        key = prop.key.removeprefix("fcemu.")
        if key in changes:
            prop.value = changes[key]
    path = tmp_path / "policy.onnx"
    onnx.save(model, str(path))
    return path


def _export(args, capsys) -> tuple[int, str]:
    code = main(["export", *args])
    return code, capsys.readouterr().err


def test_the_shipped_policy_s_contract_is_one_the_patch_honours():
    contract = check_contract(SHIPPED)
    assert contract["loop_rate_hz"] == 1000.0
    assert set(contract["fields"]) <= {"rate_error", "rotor_speed", "rate_error_integral", "rate_error_rms",
                                       "motor_output"}
    # Betaflight's motor_poles and the top speed the observation scales to 1: the Iris's, from its file
    motors = (contract["airframe"], contract["motor_poles"], contract["max_rotor_speed_rad_s"])
    assert motors == ("iris", 14, 1100.0)
    assert "- `set motor_poles = 14` (iris's motors)" in readme({
        "model": str(SHIPPED), "contract": contract, "builds": {}})


def test_without_a_pole_count_the_setup_asks_for_the_motors():
    assert motors_of("crazyflie", 1 / 2274.0)["motor_poles"] is None  # brushed: no eRPM to convert
    assert motors_of("an-airframe-not-shipped", 1 / 1000.0) == {
        "airframe": "an-airframe-not-shipped", "motor_poles": None, "max_rotor_speed_rad_s": 1000.0}


def test_a_policy_for_another_loop_rate_is_refused_before_anything_is_written(tmp_path, capsys):
    policy = _with_metadata(tmp_path, loop_rate_hz="500.0")
    out = tmp_path / "bf"
    code, err = _export([str(policy), "--target", "betaflight", "--out", str(out)], capsys)
    assert code == 2
    assert err.startswith("fcemu: error: ") and err.count("\n") == 1
    assert "500 Hz" in err and "1000 Hz" in err
    assert not out.exists()


def test_a_policy_observing_a_field_the_firmware_lacks_is_refused(tmp_path, capsys):
    meta = {p.key: p.value for p in onnx.load(str(SHIPPED)).metadata_props}
    observation = json.loads(meta["fcemu.observation"])
    observation["fields"] = ["attitude", *observation["fields"]]  # first: the error shows 40 characters
    policy = _with_metadata(tmp_path, observation=json.dumps(observation))
    code, err = _export([str(policy), "--target", "betaflight", "--out", str(tmp_path / "bf")], capsys)
    assert code == 2
    assert err.startswith("fcemu: error: ") and err.count("\n") == 1
    assert "attitude" in err


def test_an_unknown_betaflight_target_is_refused(tmp_path, capsys):
    code, err = _export([str(SHIPPED), "--target", "betaflight", "--out", str(tmp_path / "bf"),
                         "--betaflight-targets", "STM32F999"], capsys)
    assert code == 2 and "STM32F999" in err and err.count("\n") == 1


def test_the_patch_applies_to_the_package_s_betaflight_unchanged():
    apply_patch(betaflight_source(), dry_run=True)  # checks only: the package is never written to


def test_the_neural_mode_s_health_limits_default_to_the_firmware_s():
    patch = PATCH.read_text()
    defaults = {k: int(v) for k, v in re.findall(r"^\+    \.(\w+) = (\d+),", patch, re.MULTILINE)}
    rules = {f.name: f.default for f in fields(HealthRules)}
    assert defaults == {"esc_max_age_ms": round(rules["esc_max_age_s"] * 1000),
                        "esc_loss_window_ms": round(rules["esc_loss_window_s"] * 1000),
                        "esc_loss_max_percent": round(rules["esc_loss_max"] * 100),
                        "gyro_max_age_ms": round(rules["gyro_max_age_s"] * 1000),
                        "esc_max_lag_us": round(rules["esc_max_lag_s"] * 1e6)}
    setup = readme({"model": str(SHIPPED), "contract": check_contract(SHIPPED), "builds": {}})
    for setting in ("neural_esc_max_age_ms", "neural_esc_loss_win_ms", "neural_esc_loss_max",
                    "neural_gyro_max_age_ms", "neural_esc_max_lag_us"):
        assert f'{{ "{setting}",' in patch and f"`{setting}`" in setup


def test_the_lag_rule_s_motor_model_is_the_policy_airframe_s_and_none_without_one():
    header = health_header(check_contract(SHIPPED))
    defines = dict(re.findall(r"^#define (\w+) (\S+)", header, re.MULTILINE))
    values = {k: float.fromhex(v.removesuffix("f")) if "0x" in v else int(v) for k, v in defines.items()}
    iris = HealthRules.for_airframe(airframe_spec("iris"))
    assert values["NEURAL_MOTOR_MODEL"] == 1
    motor = [values[f"NEURAL_MOTOR_{k}"]
             for k in ("MAX_SPEED", "PWM_MIN", "PWM_MAX", "TAU_UP_S", "TAU_DOWN_S")]
    assert motor == pytest.approx([iris.rotor_speed_max, iris.pwm_min, iris.pwm_max, iris.motor_tau_up_s,
                                   iris.motor_tau_down_s], rel=1e-7)  # float32 literals
    assert (values["NEURAL_LAG_BASE_TICKS"], values["NEURAL_LAG_TICKS"]) == (6, iris.esc_lag_ticks)
    assert values["NEURAL_LAG_AHEAD_TICKS"] == round(iris.esc_max_age_s * 1000)  # HealthMonitor's reach
    assert values["NEURAL_LAG_MISFIT"] == pytest.approx(iris.esc_lag_misfit, rel=1e-7)
    unknown = health_header({**check_contract(SHIPPED), "airframe": None,
                             "motor_model": motor_model_of("an-airframe-not-shipped")})
    assert "#define NEURAL_MOTOR_MODEL 0" in unknown and "NEURAL_MOTOR_TAU_UP_S" not in unknown


@pytest.fixture(scope="module")
def stm32_export():
    """Both images, built by `fcemu export` in the background since collection (stm32_build)."""
    require_codegen()
    if shutil.which("arm-none-eabi-gcc") is None or shutil.which("arm-none-eabi-size") is None:
        _missing("arm-none-eabi-gcc")
    return stm32_build.result(timeout_s=460)


@pytest.mark.slow
@pytest.mark.timeout(480)  # the first may wait for the build: 270 s on two busy cores
@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.target)
def test_the_stm32_image_builds_with_the_policy_in_it_and_fits_the_chip(stm32_export, chip):
    out, manifest = stm32_export
    build = manifest["builds"][chip.target]
    hex_image = out / "betaflight" / "obj" / f"betaflight_4.6.0_{chip.target}.hex"
    assert hex_image.is_file() and hex_image.stat().st_size > 100_000
    symbols = subprocess.run(["arm-none-eabi-nm", build["elf"]], capture_output=True, text=True).stdout
    for name in ("fcemu_net", "fcemu_policy_step"):
        assert f" {name}\n" in symbols, f"{name} is not in the {chip.target} image"
    size = json.loads((out / "size.json").read_text())[chip.target]
    assert size["text"] > 0 and size["bss"] > 0
    assert size["flash_bytes"] == size["text"] + size["data"] < chip.flash_bytes
    assert size["ram_bytes"] == size["data"] + size["bss"] < chip.ram_bytes
    print(f"{chip.target}: text {size['text']} data {size['data']} bss {size['bss']}; flash "
          f"{size['flash_pct']} % of {chip.flash_bytes}, RAM {size['ram_pct']} % of {chip.ram_bytes}")
