"""`fcemu bench inference --json`: DESIGN.md's keys, measured on a real onnxruntime session."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from tests.firmware.test_neural import linear_policy, meta


def test_bench_inference_json(tmp_path):
    model = linear_policy(tmp_path / "p.onnx", np.zeros((7, 4)), np.zeros(4), meta())
    done = subprocess.run([sys.executable, "-m", "fcemu", "bench", "inference", "--model", model,
                           "--samples", "500", "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["model"] == model
    assert 0 < result["median_us"] <= result["p99_us"]
    assert 0 < result["update_median_us"]
