"""Traces npz: round trip, and malformed files refused with a clear error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation.metrics import compute_metrics
from fcemu.sitl.traces import Traces, TracesError, load_traces, save_traces


def _traces(n: int = 3, steps: int = 50, task: str = "episodic") -> Traces:
    rng = np.random.default_rng(7)
    t = np.arange(steps) * 0.001
    sp = np.repeat(rng.uniform(-5, 5, (n, 1, 3)), steps, axis=1)
    rate = sp * (1 - np.exp(-t[None, :, None] / 0.01))
    pwm = 1500 + rng.normal(0, 20, (n, steps, 4))
    return Traces(t, sp, rate, pwm, controller="pid", seed=42, task=task, extra={"episodes": n, "note": "x"})


def test_round_trip(tmp_path: Path) -> None:
    tr = _traces()
    path = save_traces(tmp_path / "sub" / "traces", tr)
    assert path.name == "traces.npz" and path.exists()
    back = load_traces(path)
    for name in ("t", "setpoint", "rate", "pwm"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tr, name))
        assert getattr(back, name).dtype == getattr(tr, name).dtype
    assert (back.controller, back.seed, back.task) == ("pid", 42, "episodic")
    assert back.extra == {"episodes": 3, "note": "x"}
    assert back.n_episodes == 3 and back.dt == pytest.approx(0.001)


def test_saved_traces_recompute_to_the_same_metrics(tmp_path: Path) -> None:
    steps = 1000
    tr = _traces(n=20, steps=steps)
    back = load_traces(save_traces(tmp_path / "t.npz", tr))
    assert compute_metrics(back).to_json() == compute_metrics(tr).to_json()


def test_episode_slice() -> None:
    tr = _traces()
    one = tr.episode(-1)
    assert one.n_episodes == 1
    np.testing.assert_array_equal(one.rate[0], tr.rate[2])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.pop("rate"), "missing arrays"),
        (lambda d: d.update(setpoint=d["setpoint"][:, :, :2]), "setpoint must have shape"),
        (lambda d: d.update(pwm=d["pwm"][:2]), "pwm has 2 episodes"),
        (lambda d: d.update(t=d["t"][::-1]), "strictly increasing"),
        (lambda d: d.update(t=d["t"].reshape(1, -1)), "t must have shape"),
        (lambda d: d.update(rate=np.where(d["rate"] > 1, np.nan, d["rate"])), "NaN"),
        (lambda d: d.update(rate=d["rate"].astype(str)), "real numeric"),
        (lambda d: d.update(meta=np.array("{not json")), "metadata is not valid JSON"),
        (lambda d: d.update(meta=np.array('{"task": "hover"}')), "task must be one of"),
    ],
)
def test_malformed_file_refused(tmp_path: Path, change, message: str) -> None:
    tr = _traces()
    arrays = {"t": tr.t, "setpoint": tr.setpoint, "rate": tr.rate, "pwm": tr.pwm,
              "meta": np.array('{"controller": "pid"}')}
    change(arrays)
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(TracesError, match=message) as info:
        load_traces(path)
    assert str(path) in str(info.value)


def test_not_an_npz_refused(tmp_path: Path) -> None:
    path = tmp_path / "junk.npz"
    path.write_bytes(b"this is not a zip file at all")
    with pytest.raises(TracesError, match="cannot read"):
        load_traces(path)
    with pytest.raises(TracesError, match="cannot read"):
        load_traces(tmp_path / "missing.npz")


def test_pickled_object_arrays_are_not_loaded(tmp_path: Path) -> None:
    tr = _traces()
    path = tmp_path / "obj.npz"
    np.savez(path, t=tr.t, setpoint=tr.setpoint, rate=np.array([object()] * 3, dtype=object), pwm=tr.pwm)
    with pytest.raises(TracesError):
        load_traces(path)
