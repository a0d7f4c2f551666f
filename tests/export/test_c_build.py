"""`fcemu export P.onnx --target c`: the sources it writes, host parity, bad input."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from fcemu.export.c.build import CExportError, export_c, ulp_distance
from fcemu.firmware.observation import ObservationSpec
from tests.export.mcu_tools import SHIPPED, require_codegen

pytestmark = pytest.mark.no_wall_clock

ALLOWED_INCLUDES = {"<math.h>", "<stdint.h>", "<float.h>", '"fcemu_policy.h"', '"fcemu_tanh.h"'}


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, dict]:
    require_codegen()
    out = tmp_path_factory.mktemp("c")
    return out, export_c(SHIPPED, out)


def test_parity_with_onnxruntime_on_10000_observations(exported) -> None:
    out, report = exported
    stored = json.loads((out / "parity.json").read_text())
    assert stored == report
    assert report["parity_samples"] >= 10_000
    assert report["max_abs_diff"] <= 1e-5
    assert report["max_ulp"] >= 0


def test_sources_are_c99_without_heap_or_other_libraries(exported) -> None:
    out, _ = exported
    sources = [out / n for n in ("fcemu_net.c", "fcemu_tanh.h", "fcemu_policy.c", "fcemu_policy.h",
                                 "fcemu_golden.c")]
    for path in sources:
        text = path.read_text()
        includes = set(re.findall(r"#include\s+(\S+)", text))
        assert includes <= ALLOWED_INCLUDES, (path.name, includes)  # stdint.h/float.h: freestanding
        assert not re.search(r"\b(malloc|calloc|realloc|free|fopen|printf)\s*\(", text), path.name
    # Strict C99 with warnings as errors, no libc beyond libm.
    subprocess.run(["cc", "-std=c99", "-pedantic", "-Wall", "-Werror", "-Wno-unused-function", "-c",
                    str(out / "fcemu_policy.c"), "-o", str(out / "check.o")], check=True)


def test_contract_constants_come_from_the_metadata(exported) -> None:
    out, _ = exported
    header = (out / "fcemu_policy.h").read_text()
    meta = json.loads((out / "contract.json").read_text())["metadata"]
    spec = json.loads(meta["observation"])
    assert f"#define FCEMU_OBS_SIZE {ObservationSpec.from_json(meta['observation']).size}" in header
    assert f'#define FCEMU_ACTION_MAPPING "{meta["action_mapping"]}"' in header
    scale = float.fromhex(re.search(r"#define FCEMU_RATE_SCALE (\S+)f\n", header).group(1))
    assert scale == pytest.approx(spec["rate_scale"], rel=1e-7)
    golden = (out / "fcemu_golden.c").read_text()
    assert "fcemu_golden_count = 32" in golden


def test_ulp_distance() -> None:
    one = np.float32(1.0)
    assert ulp_distance(np.array([one]), np.array([np.nextafter(one, np.float32(2))]))[0] == 1
    assert ulp_distance(np.array([np.float32(-0.0)]), np.array([np.float32(0.0)]))[0] == 0
    tiny = np.float32(1e-45)
    assert ulp_distance(np.array([-tiny]), np.array([tiny]))[0] == 2


def _model_without_metadata(path: Path) -> None:
    w = numpy_helper.from_array(np.zeros((4, 7), np.float32), "w")
    node = helper.make_node("Gemm", ["observation", "w"], ["action"], transB=1)
    graph = helper.make_graph([node], "g",
                              [helper.make_tensor_value_info("observation", TensorProto.FLOAT, [1, 7])],
                              [helper.make_tensor_value_info("action", TensorProto.FLOAT, [1, 4])], [w])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)


def test_refuses_a_model_without_the_contract(tmp_path: Path) -> None:
    bare = tmp_path / "bare.onnx"
    _model_without_metadata(bare)
    with pytest.raises(CExportError, match="metadata lacks"):
        export_c(bare, tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, message", [
    (["missing.onnx"], "no policy file missing.onnx"),
    ([str(SHIPPED), "--parity-samples", "0"], "--parity-samples must be >= 1, got 0"),
])
def test_cli_user_errors(tmp_path: Path, args: list[str], message: str) -> None:
    done = subprocess.run([sys.executable, "-m", "fcemu", "export", *args, "--target", "c",
                           "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip() == f"fcemu: error: {message}"
