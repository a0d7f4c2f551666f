"""`fcemu bench mcu`: the exported policy cross-compiled for a Cortex-M4F and run in QEMU.

Steps: export the policy to C (host parity on 10,000 observations); build the harness
image (`export.c.firmware_image`) with arm-none-eabi-gcc for Cortex-M4F hard float; run
it on `qemu-system-arm -M mps2-an386` (a Cortex-M4 board) with semihosting and
`-icount shift=0`; compare the target's outputs bit for bit with the host build's and
with onnxruntime's; size the policy with `arm-none-eabi-size` on the size-probe image.

Time per inference is an estimate from the instructions the M4 executes: a third image is
traced in QEMU one instruction at a time (`export.c.trace`) and each executed instruction is
weighed with the Cortex-M4 TRM's cycle counts (`export.c.cycles`). `est_cycles` adds the
flash wait states an STM32F405's ART accelerator leaves in the steady state (5 wait states at
168 MHz, 64 cached 128-bit lines, sequential prefetch; the weights assumed read at zero wait,
as from SRAM); `est_us_at_168mhz_flash_bound` charges 5 wait states to every taken branch
into another flash line and to every 128-bit line of weights. The 480 MHz figure divides the
same M4 count by an STM32H743's clock: its Cortex-M7 issues two instructions per cycle, so
that is an upper bound there. `est_us_at_168mhz_cpi` keeps the earlier estimate, the
instruction count from `-icount` × an assumed CPI of 1.25.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from fcemu.export.c import firmware_image as image
from fcemu.export.c.build import (
    SOURCES,
    CExportError,
    export_c,
    golden_source,
    host_outputs,
    load_host_library,
    onnx_outputs,
    sample_observations,
    ulp_distance,
)
from fcemu.export.c.tanh import DEFAULT_TANH
from fcemu.export.c.trace import inference_timing

CPI = 1.25
REPORT_KEYS = ("model", "max_abs_diff", "max_ulp", "flash_bytes", "ram_bytes", "instructions_per_inference",
               "est_cycles", "est_us_at_168mhz", "est_us_at_480mhz", "est_us_at_168mhz_cpi",
               "est_us_at_168mhz_flash_bound")
CLOCKS_MHZ = {"168": 168.0, "480": 480.0}
LOOP_BUDGET_SHARE = 0.25
TARGET_VECTORS = 1024
TIMED_INFERENCES = 64
QEMU_CMD = ("qemu-system-arm", "-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic", "-monitor", "none",
            "-serial", "none", "-icount", "shift=0")
TOOLS = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-objdump", "arm-none-eabi-nm",
         "qemu-system-arm")
INSTALL_HINT = ("apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm "
                "(or `make mcu-tools`)")


def missing_tools() -> list[str]:
    return [t for t in TOOLS if shutil.which(t) is None]


def _run(cmd: list[str], what: str, timeout: float = 600) -> str:
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        raise CExportError(f"{what} timed out after {timeout:.0f} s") from exc
    if done.returncode != 0:
        raise CExportError(f"{what} failed (exit {done.returncode}): "
                           f"{(done.stderr or done.stdout).strip()[-2000:]}")
    return done.stdout


def build_images(src: Path, build: Path, n_vectors: int) -> tuple[Path, Path, Path]:
    """Cross-compile the sources once; link the harness, the size probe and the trace image."""
    build.mkdir(parents=True, exist_ok=True)
    (build / "link.ld").write_text(image.LINKER_SCRIPT)
    for name, text in (("startup.c", image.STARTUP), ("harness.c", image.HARNESS),
                       ("size_probe.c", image.SIZE_PROBE), ("trace_harness.c", image.TRACE_HARNESS)):
        (build / name).write_text(text)
    defines = [f"-DFCEMU_TIMED_INFERENCES={TIMED_INFERENCES}"]
    objects = {}
    for path in [*(src / s for s in SOURCES), build / "bench_vectors.c", build / "startup.c",
                 build / "harness.c", build / "size_probe.c", build / "trace_harness.c"]:
        obj = build / (path.stem + ".o")
        _run(["arm-none-eabi-gcc", *image.ARM_FLAGS, *defines, f"-I{src}", "-c", str(path), "-o", str(obj)],
             f"arm-none-eabi-gcc {path.name}")
        objects[path.stem] = str(obj)
    link = ["arm-none-eabi-gcc", *image.ARM_FLAGS, "-nostartfiles", "-T", str(build / "link.ld"),
            "-Wl,--gc-sections"]
    policy = [objects["fcemu_net"], objects["fcemu_policy"], objects["startup"]]
    harness, probe, trace = build / "harness.elf", build / "size_probe.elf", build / "trace.elf"
    _run([*link, *policy, objects["fcemu_golden"], objects["bench_vectors"], objects["harness"],
          "-lm", "-lc", "-lgcc", "-o", str(harness)], "linking the harness image")
    _run([*link, *policy, objects["size_probe"], "-lm", "-lc", "-lgcc", "-o", str(probe)],
         "linking the size probe")
    _run([*link, *policy, objects["bench_vectors"], objects["trace_harness"], "-lm", "-lc", "-lgcc",
          "-o", str(trace)], "linking the trace image")
    return harness, probe, trace


def image_size(elf: Path) -> dict[str, int]:
    """Berkeley `arm-none-eabi-size`: flash = text + data, static RAM = data + bss."""
    lines = _run(["arm-none-eabi-size", str(elf)], "arm-none-eabi-size").strip().splitlines()
    text, data, bss = (int(x) for x in lines[1].split()[:3])
    return {"flash_bytes": text + data, "static_ram_bytes": data + bss}


def run_qemu(elf: Path, n_vectors: int) -> dict:
    out = _run([*QEMU_CMD, "-kernel", str(elf), "-chardev", f"file,id=semihosting,path={elf}.out",
                "-semihosting-config", "enable=on,target=native,chardev=semihosting"], "qemu-system-arm")
    out = Path(f"{elf}.out").read_text()
    lines = [line.split() for line in out.splitlines() if line.strip()]
    by_tag = {}
    outputs = np.zeros((n_vectors, 4), dtype=np.uint32)
    for parts in lines:
        if parts[0] == "G":
            outputs[int(parts[1])] = [int(h, 16) for h in parts[2:6]]
        else:
            by_tag[parts[0]] = parts[1:]
    if "DONE" not in by_tag:
        raise CExportError(f"the QEMU run did not finish: {out.strip()[-500:]}")
    cal_ticks, cal_insns = (int(x) for x in by_tag["CAL"])
    t_infer, t_empty, n = (int(x) for x in by_tag["TIME"])
    insns_per_tick = cal_insns / cal_ticks
    return {
        "outputs": outputs.view(np.float32),
        "self_test_failures": int(by_tag["SELFTEST"][0]),
        "self_test_max_abs_diff": float(np.uint32(int(by_tag["SELFTEST"][1], 16)).view(np.float32)),
        "stack_bytes": int(by_tag["STACK"][0]),
        "instructions_per_inference": round((t_infer - t_empty) * insns_per_tick / n),
        "instructions_per_tick": insns_per_tick,
    }


def bench_mcu(model: str | Path | None = None, out: str | Path | None = None,
              parity_samples: int = 10_000, target_vectors: int = TARGET_VECTORS,
              tanh: str = DEFAULT_TANH) -> dict:
    """`REPORT_KEYS` (what `fcemu bench mcu --json` prints) and the details behind them, which
    also go to OUT/mcu.json when `out` is given."""
    from fcemu.firmware.controllers import DEFAULT_POLICY

    model = Path(model) if model is not None else DEFAULT_POLICY
    missing = missing_tools()
    if missing:
        raise CExportError(f"{', '.join(missing)} not found; {INSTALL_HINT}")
    with tempfile.TemporaryDirectory(prefix="fcemu_mcu_") as tmp:
        root = Path(out) if out is not None else Path(tmp)
        src, build = root / "c", root / "build"
        parity = export_c(model, src, parity_samples, tanh)
        contract = json.loads((src / "contract.json").read_text())
        from fcemu.firmware.observation import ObservationSpec

        spec = ObservationSpec.from_json(contract["metadata"]["observation"])
        obs = sample_observations(spec, target_vectors, seed=1)
        (build).mkdir(parents=True, exist_ok=True)
        (build / "bench_vectors.c").write_text(
            golden_source(obs, np.zeros((len(obs), 4), np.float32), prefix="bench"))
        harness, probe, trace = build_images(src, build, len(obs))
        target = run_qemu(harness, len(obs))
        timing = inference_timing(trace, build / "fcemu_net.o")
        reference = onnx_outputs(model, obs)
        host = host_outputs(load_host_library(src / "libfcemu_policy.so"), obs)
        size = image_size(probe)
    if target["self_test_failures"]:
        raise CExportError(f"the on-target self-test failed on {target['self_test_failures']} outputs "
                           f"(max |diff| {target['self_test_max_abs_diff']:.2e})")
    ours = target["outputs"]
    instructions = target["instructions_per_inference"]
    est_cycles = timing["cycles"] + timing["art_wait_cycles"]
    report = {
        "model": str(model),
        "max_abs_diff": max(parity["max_abs_diff"], float(np.max(np.abs(ours - reference)))),
        "max_ulp": max(parity["max_ulp"], int(ulp_distance(ours, reference).max())),
        "flash_bytes": size["flash_bytes"],
        "ram_bytes": size["static_ram_bytes"] + target["stack_bytes"],
        "instructions_per_inference": instructions,
        "est_cycles": est_cycles,
        "est_us_at_168mhz": round(est_cycles / CLOCKS_MHZ["168"], 1),
        "est_us_at_480mhz": round(est_cycles / CLOCKS_MHZ["480"], 1),
        "est_us_at_168mhz_cpi": round(instructions * CPI / CLOCKS_MHZ["168"], 1),
        "est_us_at_168mhz_flash_bound": round(timing["flash_bound_cycles"] / CLOCKS_MHZ["168"], 1),
    }
    details = {
        **report, "cpi_assumed": CPI, "tanh": tanh, "cycles": timing,
        "host": {k: parity[k] for k in ("parity_samples", "max_abs_diff", "max_ulp")},
        "target": {"vectors": len(obs), "max_abs_diff_vs_onnx": float(np.max(np.abs(ours - reference))),
                   "max_ulp_vs_onnx": int(ulp_distance(ours, reference).max()),
                   "max_abs_diff_vs_host": float(np.max(np.abs(ours - host))),
                   "max_ulp_vs_host": int(ulp_distance(ours, host).max()),
                   "self_test_max_abs_diff": target["self_test_max_abs_diff"],
                   "static_ram_bytes": size["static_ram_bytes"], "stack_bytes": target["stack_bytes"],
                   "instructions_per_timer_tick": target["instructions_per_tick"]},
    }
    if out is not None:
        (Path(out) / "mcu.json").write_text(json.dumps(details, indent=1) + "\n")
    return details


BOARDS = {"168": "STM32F405", "480": "STM32H743"}


def within_budget(report: dict, mhz: str = "168", loop_hz: float = 1000.0,
                  share: float = LOOP_BUDGET_SHARE) -> bool:
    """Whether the estimated inference takes at most `share` of the loop period at that clock."""
    return report[f"est_us_at_{mhz}mhz"] <= share * 1e6 / loop_hz


def budget_verdict(report: dict, loop_hz: float = 1000.0, share: float = LOOP_BUDGET_SHARE) -> str:
    budget_us = share * 1e6 / loop_hz
    parts = []
    for mhz, board in BOARDS.items():
        us = report[f"est_us_at_{mhz}mhz"]
        verdict = "fits" if within_budget(report, mhz, loop_hz, share) else "OVER BUDGET"
        share_used = us * loop_hz / 1e6
        parts.append(f"{board} @ {mhz} MHz: {us:.1f} µs ({share_used:.0%} of the period), {verdict}")
    return (f"budget {budget_us:.0f} µs = {share:.0%} of a {loop_hz:.0f} Hz loop (TRM cycle count): "
            + "; ".join(parts))
