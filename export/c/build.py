"""`fcemu export P.onnx --target c --out DIR`: the policy as C99 sources, checked on the host.

The network comes from emx-onnx-cgen (batch pinned to 1, every temporary on the stack,
weights inline as const arrays); the contract code from `export.c.contract`; golden
vectors from onnxruntime. The sources are then compiled with the host C compiler into
`libfcemu_policy.so` (what `--controller DIR` flies) and compared with onnxruntime on
≥ 10,000 observations; the figures go to DIR/parity.json. `tanh` picks the network's
tanh (`export.c.tanh`): the fast rational approximation (default) or libm's `tanhf`.
"""

from __future__ import annotations

import ctypes
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort

from fcemu.export.c.contract import (
    ACTION_SIZE,
    NET_FUNCTION,
    SELF_TEST_TOLERANCE,
    Contract,
    c_float,
    contract_sources,
)
from fcemu.export.c.tanh import DEFAULT_TANH, FAST_TANH_HEADER, TANH_CHOICES, TANH_HEADER, use_fast_tanh
from fcemu.firmware.neural import NeuralRateController, PolicyContractError
from fcemu.firmware.observation import FIELD_DEFS

SOURCES = ("fcemu_net.c", "fcemu_policy.c", "fcemu_golden.c")
HOST_LIBRARY = "libfcemu_policy.so"
C_FLAGS = ("-std=c99", "-O2", "-ffp-contract=off", "-Wall", "-Wextra", "-Wno-unused-parameter")
GOLDEN_COUNT = 32


class CExportError(ValueError):
    """A policy that cannot be exported to C, or a toolchain step that failed, with the reason."""


def sample_observations(spec, n: int, seed: int = 0) -> np.ndarray:
    """Observations over and beyond the flown range: scaled rate errors in ±3, rotor speeds
    0..1.2 of the maximum, motor outputs over their whole range 0..1, loop delays 0..6 ticks, authority
    estimates −0.5..3 (a whoop's roll reads about 2; the policy's input clip sits inside these)."""
    rng = np.random.default_rng(seed)
    ranges = {"rate_error": (-3.0, 3.0), "rotor_speed": (0.0, 1.2), "rate_error_integral": (-3.0, 3.0),
              "rate_error_rms": (0.0, 3.0), "motor_output": (0.0, 1.0), "rate": (-3.0, 3.0),
              "loop_delay": (0.0, 1.2), "authority": (-0.5, 3.0)}
    cols = [rng.uniform(*ranges[f], size=(n, spec.memory, FIELD_DEFS[f].size)) for f in spec.fields]
    return np.concatenate(cols, axis=-1).reshape(n, spec.size).astype(np.float32)


def ulp_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How many float32 values lie between a and b (0 when equal)."""
    def ordered(x: np.ndarray) -> np.ndarray:
        i = np.ascontiguousarray(x, dtype=np.float32).view(np.int32).astype(np.int64)
        return np.where(i < 0, -(i & 0x7FFFFFFF), i)
    return np.abs(ordered(a) - ordered(b))


def run_emx(model: Path, out_c: Path) -> None:
    cmd = [sys.executable, "-m", "emx_onnx_cgen", "compile", str(model), str(out_c),
           "--model-name", NET_FUNCTION, "--input-dim", "batch=1", "--color", "never",
           "--large-temp-threshold", "0",  # no heap: every temporary on the stack
           "--large-weight-threshold", "0"]  # weights inline in the source, no data file
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    except FileNotFoundError as exc:
        raise CExportError(f"cannot run emx-onnx-cgen ({exc}); pip install 'fcemu[mcu]'") from exc
    if done.returncode != 0:
        if "No module named emx_onnx_cgen" in done.stderr:
            raise CExportError("emx-onnx-cgen is not installed; pip install 'fcemu[mcu]'")
        tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
        raise CExportError(f"emx-onnx-cgen failed on {model}: {' | '.join(tail)}")


def golden_source(obs: np.ndarray, action: np.ndarray, prefix: str = "fcemu_golden") -> str:
    def rows(a: np.ndarray) -> str:
        return ",\n".join("    {" + ", ".join(c_float(x) for x in row) + "}" for row in a)
    return (f"/* Observations and the ONNX Runtime outputs for them. */\n"
            f'#include "fcemu_policy.h"\n\n'
            f"const int {prefix}_count = {len(obs)};\n"
            f"const float {prefix}_obs[{len(obs)}][FCEMU_OBS_SIZE] = {{\n{rows(obs)}\n}};\n"
            f"const float {prefix}_action[{len(obs)}][FCEMU_ACTION_SIZE] = {{\n{rows(action)}\n}};\n")


def compile_host(out_dir: Path, cc: str = "cc") -> Path:
    if shutil.which(cc) is None:
        raise CExportError(f"no host C compiler {cc!r} on PATH (install gcc)")
    lib = out_dir / HOST_LIBRARY
    cmd = [cc, *C_FLAGS, "-fPIC", "-shared", "-o", str(lib), *(str(out_dir / s) for s in SOURCES), "-lm"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise CExportError(f"host compile failed: {done.stderr.strip()[:2000]}")
    return lib


def load_host_library(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    f32p = ctypes.POINTER(ctypes.c_float)
    lib.fcemu_policy_infer.argtypes = [f32p, f32p]
    lib.fcemu_policy_infer.restype = None
    return lib


def host_outputs(lib: ctypes.CDLL, obs: np.ndarray) -> np.ndarray:
    obs = np.ascontiguousarray(obs, dtype=np.float32)
    out = np.zeros((len(obs), ACTION_SIZE), dtype=np.float32)
    f32p = ctypes.POINTER(ctypes.c_float)
    infer, out_base = lib.fcemu_policy_infer, out.ctypes.data
    step_in, step_out = obs.strides[0], out.strides[0]
    for n in range(len(obs)):
        infer(ctypes.cast(obs.ctypes.data + n * step_in, f32p), ctypes.cast(out_base + n * step_out, f32p))
    return out


def onnx_outputs(model: Path, obs: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name
    return np.asarray(session.run(None, {name: obs})[0], dtype=np.float32)


def load_contract(model: Path) -> tuple[Contract, dict[str, str]]:
    try:
        policy = NeuralRateController(model)
    except PolicyContractError as exc:
        raise CExportError(str(exc)) from exc
    outputs = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"]).get_outputs()
    if len(outputs) != 1:
        raise CExportError(f"{model}: {len(outputs)} outputs; the C export takes a policy with one")
    return Contract(policy.spec, policy.action_mapping, policy.trained_rate_hz), policy.metadata


def choose_tanh(net_c: Path, tanh: str) -> None:
    """Point the generated network at the chosen tanh (see `export.c.tanh`)."""
    header = net_c.parent / TANH_HEADER
    header.unlink(missing_ok=True)
    if tanh == "libm":
        return
    try:
        source = use_fast_tanh(net_c.read_text())
    except ValueError as exc:
        raise CExportError(str(exc)) from exc
    if TANH_HEADER in source:
        header.write_text(FAST_TANH_HEADER)
        net_c.write_text(source)


def export_c(model: str | Path, out_dir: str | Path, parity_samples: int = 10_000,
             tanh: str = DEFAULT_TANH) -> dict:
    """Write the C sources, build them for the host, check parity; returns the parity report."""
    model, out_dir = Path(model), Path(out_dir)
    if not model.exists():
        raise CExportError(f"no policy file {model}")
    if parity_samples < 1:
        raise CExportError(f"--parity-samples must be >= 1, got {parity_samples}")
    if tanh not in TANH_CHOICES:
        raise CExportError(f"--tanh must be one of {', '.join(TANH_CHOICES)}, got {tanh!r}")
    contract, metadata = load_contract(model)
    out_dir.mkdir(parents=True, exist_ok=True)
    run_emx(model, out_dir / "fcemu_net.c")
    choose_tanh(out_dir / "fcemu_net.c", tanh)
    for name, text in contract_sources(contract).items():
        (out_dir / name).write_text(text)
    obs = sample_observations(contract.spec, max(parity_samples, GOLDEN_COUNT))
    reference = onnx_outputs(model, obs)
    (out_dir / "fcemu_golden.c").write_text(golden_source(obs[:GOLDEN_COUNT], reference[:GOLDEN_COUNT]))
    (out_dir / "contract.json").write_text(json.dumps(
        {"model": str(model), "metadata": metadata, "tanh": tanh, "self_test_tolerance": SELF_TEST_TOLERANCE},
        indent=1))
    lib = load_host_library(compile_host(out_dir))
    ours = host_outputs(lib, obs)
    report = {
        "model": str(model), "out": str(out_dir), "compiler": "cc " + " ".join(C_FLAGS), "tanh": tanh,
        "parity_samples": len(obs),
        "max_abs_diff": float(np.max(np.abs(ours - reference))),
        "max_ulp": int(ulp_distance(ours, reference).max()),
    }
    (out_dir / "parity.json").write_text(json.dumps(report, indent=1) + "\n")
    return report
