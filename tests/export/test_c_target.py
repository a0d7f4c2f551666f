"""`fcemu bench mcu`: the exported policy on a Cortex-M4F in QEMU, and the timing budget."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from fcemu.export.c.target import REPORT_KEYS, bench_mcu, budget_verdict, within_budget
from tests.export.mcu_tools import SHIPPED, require_target_tools


@pytest.fixture(scope="module")
def shipped(tmp_path_factory) -> tuple[dict, dict]:
    """`fcemu bench mcu --json` as a user runs it, and the details it stored."""
    require_target_tools()
    out = tmp_path_factory.mktemp("mcu")
    done = subprocess.run([sys.executable, "-m", "fcemu", "bench", "mcu", "--json", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout), json.loads((out / "mcu.json").read_text())


def shipped_layers() -> list[int]:
    """The shipped actor's widths, input to output (its Gemms' weights)."""
    graph = onnx.load(str(SHIPPED)).graph
    weights = {w.name: numpy_helper.to_array(w) for w in graph.initializer}
    shapes = []
    for g in (n for n in graph.node if n.op_type == "Gemm"):
        w = weights[g.input[1]]
        shapes.append(w.shape[::-1] if any(a.name == "transB" and a.i for a in g.attribute) else w.shape)
    return [int(shapes[0][0]), *(int(s[1]) for s in shapes)]


def shipped_macs() -> int:
    return sum(a * b for a, b in itertools.pairwise(shipped_layers()))


def oversized_policy(path: Path, width: int = 192) -> None:
    """Two tanh layers of `width` (192: over 39 k multiply-adds, 8× or more the shipped policy's),
    the shipped contract."""
    rng = np.random.default_rng(0)
    sizes, nodes, inits, x = [shipped_layers()[0], width, width, 4], [], [], "observation"
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        w = (rng.standard_normal((n_out, n_in)) / np.sqrt(n_in)).astype(np.float32)
        b = np.zeros(n_out, np.float32)
        inits += [numpy_helper.from_array(w, f"w{i}"), numpy_helper.from_array(b, f"b{i}")]
        last = i == len(sizes) - 2
        y = "action" if last else f"z{i}"
        nodes.append(helper.make_node("Gemm", [x, f"w{i}", f"b{i}"], [y], transB=1))
        if not last:
            nodes.append(helper.make_node("Tanh", [f"z{i}"], [f"h{i}"]))
            x = f"h{i}"
    graph = helper.make_graph(
        nodes, "oversized",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", sizes[0]])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 4])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    for prop in onnx.load(SHIPPED).metadata_props:
        model.metadata_props.append(prop)
    onnx.save(model, path)


def test_json_has_exactly_the_documented_keys(shipped) -> None:
    report, _ = shipped
    assert tuple(report) == REPORT_KEYS
    assert report["model"] == str(SHIPPED)


def test_on_target_parity(shipped) -> None:
    report, details = shipped
    assert report["max_abs_diff"] <= 1e-5
    assert details["host"]["parity_samples"] >= 10_000
    target = details["target"]
    assert target["vectors"] >= 1000
    assert target["max_abs_diff_vs_onnx"] <= 1e-5
    # The same C with no libm call in the network (fast tanh): IEEE float32 on both, bit for bit.
    assert details["tanh"] == "fast"
    assert target["max_ulp_vs_host"] == 0
    assert target["self_test_max_abs_diff"] <= 1e-5


def test_size_and_instruction_count_are_plausible(shipped) -> None:
    report, details = shipped
    macs = shipped_macs()
    weights = (macs + sum(shipped_layers()[1:])) * 4
    assert weights < report["flash_bytes"] < weights + 16_384
    assert 0 < details["target"]["stack_bytes"] < 4096
    assert report["ram_bytes"] == details["target"]["static_ram_bytes"] + details["target"]["stack_bytes"]
    assert 2 * macs < report["instructions_per_inference"] < 20 * macs
    assert details["target"]["instructions_per_timer_tick"] == pytest.approx(40.0)  # 1 GHz icount / 25 MHz


def test_shipped_policy_timing_budget(shipped) -> None:
    """A 1 kHz loop with 25 % of the period for the policy: by the M4 cycle count the shipped
    policy fits on the STM32H743 and on the STM32F405 (the deployable bar's budget)."""
    report, details = shipped
    assert within_budget(report, "480") and within_budget(report, "168")
    assert report["est_us_at_168mhz"] <= 250.0
    assert report["est_us_at_168mhz"] == pytest.approx(report["est_us_at_480mhz"] * 480 / 168, rel=1e-2)
    verdict = budget_verdict(report)
    assert "STM32F405 @ 168 MHz" in verdict and "STM32H743 @ 480 MHz" in verdict
    assert verdict.count("OVER BUDGET") == (not within_budget(report, "168"))
    assert details["cpi_assumed"] == 1.25
    assert report["est_us_at_168mhz_cpi"] == round(report["instructions_per_inference"] * 1.25 / 168, 1)


def test_cycle_estimate_of_the_shipped_policy(shipped) -> None:
    """The traced inference is the one `-icount` counts, every instruction is in the TRM tables,
    and the figures are ordered: TRM band around the estimate, the flash bound above it."""
    report, details = shipped
    cycles = details["cycles"]
    assert cycles["calls_traced"] >= 2 and not cycles["unpriced"]
    assert cycles["instructions"] == pytest.approx(report["instructions_per_inference"], rel=0.02)
    assert cycles["cycles_low"] <= cycles["cycles"] <= cycles["cycles_high"]
    assert report["est_cycles"] == cycles["cycles"] + cycles["art_wait_cycles"]
    instructions = report["instructions_per_inference"]
    assert instructions < report["est_cycles"] < 3 * instructions
    assert report["est_us_at_168mhz"] == round(report["est_cycles"] / 168, 1)
    assert report["est_us_at_168mhz"] < report["est_us_at_168mhz_flash_bound"]
    macs = shipped_macs()
    assert cycles["histogram"]["vmul"] >= macs and cycles["histogram"]["vldr"] >= macs
    assert cycles["constant_bytes"] >= 4 * macs


def test_oversized_network_is_reported_over_budget(tmp_path: Path) -> None:
    require_target_tools()
    oversized_policy(tmp_path / "big.onnx")
    report = bench_mcu(tmp_path / "big.onnx", parity_samples=1000, target_vectors=16)
    assert not within_budget(report, "168")
    assert not within_budget(report, "480")
    assert report["instructions_per_inference"] > 2 * 39_000
    assert budget_verdict(report).count("OVER BUDGET") == 2
    assert report["max_abs_diff"] <= 1e-5


def test_cli_reports_a_bad_model(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "fcemu", "bench", "mcu", "--model", str(tmp_path / "no.onnx")]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.startswith("fcemu: error: ") and done.stderr.count("\n") == 1
