"""`export.c.tanh`: the fast tanh's accuracy over float32, and the export with either tanh."""

from __future__ import annotations

import ctypes
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fcemu.export.c.build import export_c, ulp_distance
from fcemu.export.c.tanh import FAST_TANH_HEADER, TANH_HEADER, use_fast_tanh
from tests.export.mcu_tools import SHIPPED, require_codegen

pytestmark = pytest.mark.no_wall_clock

F32P = ctypes.POINTER(ctypes.c_float)
FAST_TANH_MAX_ULP = 7  # measured on every float32 in [-10, 10] against the correctly rounded tanh


@pytest.fixture(scope="module")
def fast_tanh(tmp_path_factory) -> ctypes.CDLL:
    require_codegen()
    root = tmp_path_factory.mktemp("tanh")
    (root / TANH_HEADER).write_text(FAST_TANH_HEADER)
    (root / "many.c").write_text(
        f'#include <math.h>\n#include "{TANH_HEADER}"\n'
        "void fast_tanh_many(const float *x, float *y, long n) {\n"
        "    for (long i = 0; i < n; ++i) y[i] = fcemu_tanhf(x[i]);\n}\n")
    subprocess.run(["cc", "-std=c99", "-pedantic", "-Wall", "-Werror", "-O2", "-ffp-contract=off", "-fPIC",
                    "-shared", "-o", str(root / "many.so"), str(root / "many.c")], check=True)
    lib = ctypes.CDLL(str(root / "many.so"))
    lib.fast_tanh_many.argtypes = [F32P, F32P, ctypes.c_long]
    return lib


def _apply(lib: ctypes.CDLL, x: np.ndarray) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float32)
    y = np.empty_like(x)
    lib.fast_tanh_many(x.ctypes.data_as(F32P), y.ctypes.data_as(F32P), len(x))
    return y


def test_fast_tanh_within_7_ulp_on_a_dense_float32_sample(fast_tanh) -> None:
    """Every 61st float32 in [0, 10] and its negative (tanh is odd; the code is too)."""
    top = np.array([10.0], np.float32).view(np.int32)[0]
    positive = np.arange(0, top + 1, 61, dtype=np.int32).view(np.float32)
    x = np.concatenate([positive, -positive, np.float32([10.0, -10.0, 7.9053111, 4e-4, -4e-4])])
    exact = np.tanh(x.astype(np.float64)).astype(np.float32)
    ulp = ulp_distance(_apply(fast_tanh, x), exact)
    assert len(x) > 30_000_000
    assert ulp.max() <= FAST_TANH_MAX_ULP
    assert np.median(ulp) <= 1


def test_fast_tanh_limits(fast_tanh) -> None:
    x = np.float32([0.0, -0.0, 1e-30, -3e-4, 8.0, -8.0, 1e30, -np.inf, np.inf, np.nan])
    y = _apply(fast_tanh, x)
    np.testing.assert_array_equal(y[:4], x[:4])  # tanh(x) rounds to x near 0
    np.testing.assert_array_equal(y[4:9], np.float32([1, -1, 1, -1, 1]))
    assert np.isnan(y[9])


def test_use_fast_tanh_rewrites_the_libm_calls() -> None:
    source = ("#include <math.h>\n\nstatic inline float ref_scalar_f32_tanh(float a) {\n"
              "    return tanhf(a);\n}\nfloat keep(float a) { return my_tanhf(a) + x.tanhf; }\n")
    out = use_fast_tanh(source)
    assert f'#include <math.h>\n#include "{TANH_HEADER}"\n' in out
    assert "return fcemu_tanhf(a);" in out and "my_tanhf(a) + x.tanhf" in out
    assert use_fast_tanh("float f(float a) { return a; }\n") == "float f(float a) { return a; }\n"
    with pytest.raises(ValueError, match=r"does not include <math\.h>"):
        use_fast_tanh("float f(float a) { return tanhf(a); }\n")


@pytest.mark.parametrize("tanh", ["fast", "libm"])
def test_export_with_either_tanh_keeps_parity(tmp_path: Path, tanh: str) -> None:
    require_codegen()
    report = export_c(SHIPPED, tmp_path, parity_samples=10_000, tanh=tanh)
    net = (tmp_path / "fcemu_net.c").read_text()
    assert report["tanh"] == json.loads((tmp_path / "contract.json").read_text())["tanh"] == tanh
    assert report["max_abs_diff"] <= 1e-5
    if tanh == "fast":
        assert (tmp_path / TANH_HEADER).exists() and "fcemu_tanhf(" in net
        assert "tanhf(" not in net.replace("fcemu_tanhf(", "")
    else:
        assert not (tmp_path / TANH_HEADER).exists() and "tanhf(" in net
