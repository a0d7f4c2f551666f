"""Export a Stable-Baselines3 checkpoint to the ONNX file the firmware flies.

The exported graph is the deterministic actor with the training run's observation
normalisation folded in: raw observation (as `firmware.observation` builds it) in,
unclipped action out. A run trained without an observation clip (`--obs-clip 0`) has
its normalisation folded into the first layer's weights, so the graph is the bare MLP:
every node costs the firmware about half a microsecond of onnxruntime dispatch per tick.
The file's metadata carries the contract `firmware.neural` checks, with the airframe the run
trained on and the envelope of airframes its randomisation spanned. A parity check
against the unfolded actor in torch on ≥ 10,000 observations is printed and stored: within
1e-5, or four times the float32 actor's own distance from float64 where that is larger.
"""

from __future__ import annotations

import json
import pickle
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch import nn

from fcemu import __version__
from fcemu.firmware.airframe_spec import AirframeSpec, Envelope
from fcemu.firmware.contract import MAX_LOOP_DELAY_TICKS
from fcemu.firmware.neural import META_PREFIX, NeuralRateController
from fcemu.firmware.observation import ObservationSpec, observe_step
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME
from fcemu.sim_bridge.airframe_spec import airframe_spec, envelope

ALGORITHMS = ("ppo", "trpo", "ddpg", "td3", "sac")
PARITY_TOLERANCE = 1e-5
OWN_ERROR_FACTOR = 4.0  # how far past the float32 actor's own error from float64 a graph may be


class ExportError(ValueError):
    """A checkpoint that cannot be exported, with the reason."""


@dataclass
class Checkpoint:
    model_path: Path
    vecnormalize_path: Path | None
    config: dict


def find_checkpoint(target: str | Path) -> Checkpoint:
    """A run directory (its final model) or one checkpoint .zip inside a run."""
    target = Path(target)
    if target.is_dir():
        run_dir, model = target, target / "model.zip"
        vecnorm = run_dir / "vecnormalize.pkl"
    elif target.suffix == ".zip":
        model = target
        run_dir = target.parent.parent if target.parent.name == "checkpoints" else target.parent
        prefix, _, steps = target.stem.rpartition("_steps")[0].rpartition("_")
        vecnorm = target.with_name(f"{prefix}_vecnormalize_{steps}_steps.pkl")
        if not vecnorm.exists():
            vecnorm = run_dir / "vecnormalize.pkl"
    else:
        raise ExportError(f"{target}: give a run directory or a checkpoint .zip")
    if not model.exists():
        raise ExportError(f"{model}: no such checkpoint")
    config_path = run_dir / "config.json"
    if not config_path.exists():
        raise ExportError(f"{config_path} missing: it records the observation spec, action mapping and "
                          "algorithm; only runs made by `fcemu train` can be exported")
    config = json.loads(config_path.read_text())
    return Checkpoint(model, vecnorm if vecnorm.exists() else None, config)


def load_model(checkpoint: Checkpoint):
    algo = checkpoint.config.get("algo", "").lower()
    if algo not in ALGORITHMS:
        raise ExportError(f"algorithm {algo!r} in {checkpoint.model_path.parent}: export knows {ALGORITHMS}")
    if algo == "trpo":
        from sb3_contrib import TRPO as cls
    else:
        import stable_baselines3

        cls = getattr(stable_baselines3, algo.upper())
    try:
        return cls.load(checkpoint.model_path, device="cpu")
    except Exception as exc:  # SB3 raises many types for a corrupt or foreign zip
        raise ExportError(f"{checkpoint.model_path}: cannot load as {algo.upper()} ({exc})") from exc


class DeterministicActor(nn.Module):
    """Normalisation + the policy's deterministic action, as one traceable module."""

    def __init__(self, model, obs_mean: np.ndarray, obs_var: np.ndarray, clip_obs: float, eps: float) -> None:
        super().__init__()
        self.policy = model.policy
        self.on_policy = hasattr(self.policy, "action_net")
        self.register_buffer("mean", torch.as_tensor(obs_mean, dtype=torch.float32))
        self.register_buffer("inv_std", torch.as_tensor(1.0 / np.sqrt(obs_var + eps), dtype=torch.float32))
        self.clip_obs = float(clip_obs)  # inf: no clip
        self.squash = self.on_policy and bool(getattr(self.policy, "squash_output", False))
        self.flat = self.on_policy and isinstance(self.policy.pi_features_extractor, FlattenExtractor) \
            and len(getattr(model.observation_space, "shape", ())) == 1

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = (obs - self.mean) * self.inv_std
        if np.isfinite(self.clip_obs):
            x = torch.clamp(x, -self.clip_obs, self.clip_obs)
        if self.on_policy:  # PPO, TRPO: the Gaussian's mean
            # A flat Box observation goes through SB3's extractor as Cast + Flatten, both no-ops
            # here; leaving them out saves the firmware two graph nodes per tick.
            features = x if self.flat else self.policy.extract_features(x, self.policy.pi_features_extractor)
            mean = self.policy.action_net(self.policy.mlp_extractor.forward_actor(features))
            return torch.tanh(mean) if self.squash else mean  # gSDE's squash_output: the mode is tanh(mean)
        return self.policy.actor(x, deterministic=True) if _is_sac(self.policy) else self.policy.actor(x)


class FoldedActor(nn.Module):
    """A flat on-policy actor without a clip, its normalisation folded into the first layer:
    W' = W·diag(1/σ), b' = b − W'·μ (in float64, then float32), the rest of the layers as trained.
    `centred`: only 1/σ is folded and μ is subtracted in the graph, so W'·(x − μ) does not
    cancel against a large b' in float32 (one graph node, where the unfolded actor has two)."""

    def __init__(self, actor: DeterministicActor, centred: bool = False) -> None:
        super().__init__()
        layers = [*actor.policy.mlp_extractor.policy_net, actor.policy.action_net]
        first = layers[0]
        folded = nn.Linear(first.in_features, first.out_features)
        w = first.weight.detach().double() * actor.inv_std.double()[None, :]
        folded.weight.data = w.float()
        folded.bias.data = first.bias.detach().clone() if centred \
            else (first.bias.detach().double() - w @ actor.mean.double()).float()
        self.register_buffer("mean", actor.mean.clone() if centred else None)
        self.net = nn.Sequential(folded, *layers[1:])
        self.squash = actor.squash

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        mean = self.net(obs if self.mean is None else obs - self.mean)
        return torch.tanh(mean) if self.squash else mean


FOLDED, CENTRED, UNFOLDED = ("folded into the first layer",
                             "1/σ folded into the first layer, μ subtracted in the graph", "in the graph")


def graph_modules(actor: DeterministicActor) -> list[tuple[str, nn.Module]]:
    """What may be exported, cheapest graph first; `export_policy` writes the first that keeps
    parity: the folds where the normalisation folds, the actor itself always last."""
    candidates = [(UNFOLDED, actor)]
    if not (actor.on_policy and actor.flat and not np.isfinite(actor.clip_obs)):
        return candidates
    first = next(iter(actor.policy.mlp_extractor.policy_net), actor.policy.action_net)
    if not isinstance(first, nn.Linear):
        return candidates
    return [(FOLDED, FoldedActor(actor).eval()), (CENTRED, FoldedActor(actor, centred=True).eval()),
            *candidates]


def _is_sac(policy) -> bool:
    return type(policy).__module__.startswith("stable_baselines3.sac")


def build_actor(model, checkpoint: Checkpoint, spec: ObservationSpec) -> DeterministicActor:
    size = spec.size
    obs_shape = getattr(model.observation_space, "shape", None)
    if obs_shape != (size,):
        raise ExportError(f"policy observation shape {obs_shape} does not match the run's spec ({size},)")
    if getattr(model.action_space, "shape", None) != (4,):
        raise ExportError(f"policy action shape {model.action_space.shape}, expected (4,)")
    mean, var, clip, eps = np.zeros(size), np.ones(size), np.inf, 0.0
    if checkpoint.vecnormalize_path is not None:
        with open(checkpoint.vecnormalize_path, "rb") as fh:
            vecnorm = pickle.load(fh)
        if vecnorm.norm_obs:
            mean, var = vecnorm.obs_rms.mean, vecnorm.obs_rms.var
            clip, eps = vecnorm.clip_obs, vecnorm.epsilon
    actor = DeterministicActor(model, mean, var, clip, eps)
    return actor.eval()


def parity_observations(spec: ObservationSpec, n: int, max_rotor_speed: float, seed: int = 0) -> np.ndarray:
    """Observations spread over what flight produces: errors to ±2× the command bound, any rotor
    speed up to the airframe's `max_rotor_speed`, loop delays of 0-5 ticks."""
    rng = np.random.default_rng(seed)
    steps = []
    # one per flight, as configured; drawn only where read, so other specs' samples stay as they were
    delay = rng.integers(0, MAX_LOOP_DELAY_TICKS + 1, n).astype(float) if spec.reads_loop_delay else None
    for _ in range(spec.memory):
        setpoint = rng.uniform(-10.5, 10.5, (n, 3))
        gyro = rng.uniform(-10.5, 10.5, (n, 3))
        rotor = rng.uniform(0.0, max_rotor_speed, (n, 4))
        steps.append(observe_step(spec, setpoint, gyro, rotor, loop_delay=delay))
    return np.concatenate(steps, axis=-1).astype(np.float32)


def _write_graph(module: nn.Module, size: int, out: Path, obs: np.ndarray, expected: np.ndarray) -> float:
    """Export `module` to `out`; the largest |onnxruntime − expected| on `obs`."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter is deprecated but needs no onnxscript
        torch.onnx.export(module, (torch.zeros(1, size),), str(out), dynamo=False,
                          input_names=["observation"], output_names=["action"], opset_version=17,
                          dynamic_axes={"observation": {0: "batch"}, "action": {0: "batch"}})
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    return float(np.abs(session.run(None, {"observation": obs})[0] - expected).max())


def trained_on(cfg: dict) -> tuple[AirframeSpec, Envelope]:
    """The airframe a run's config names and the envelope its randomisation spanned (± a margin
    where the run names no randomisation file); for a run over a pool of quads, the pool's first
    airframe, named for the pool, and the envelope around the pool."""
    airframe = cfg.get("airframe", DEFAULT_AIRFRAME)
    randomize = cfg.get("randomize")
    pool = (cfg.get("env") or {}).get("airframe_pool")
    if pool is not None:
        from dataclasses import replace

        from fcemu.sim_bridge.airframe_draw import airframe_pool

        try:
            specs = [airframe_spec(a) for a in airframe_pool(str(pool))]
        except (OSError, ValueError, KeyError) as exc:
            raise ExportError(f"the run's airframe pool {pool!r}: {exc}") from None
        return replace(specs[0], name=f"the pool {pool}"), Envelope.around(specs)
    try:
        return airframe_spec(airframe), envelope(airframe, randomize if isinstance(randomize, str) else None)
    except (OSError, ValueError, KeyError) as exc:
        raise ExportError(f"the run's airframe {airframe!r} or randomisation {randomize!r}: {exc}") from None


def record_metadata(path: str | Path, values: dict[str, str]) -> None:
    """Write `fcemu.<key>` = value for each of `values` into an exported policy's metadata, replacing
    any already there, its graph untouched."""
    proto = onnx.load(str(path))
    graph = proto.graph.SerializeToString()
    kept = [(p.key, p.value) for p in proto.metadata_props
            if p.key not in {META_PREFIX + k for k in values}]
    del proto.metadata_props[:]
    for k, v in [*kept, *((META_PREFIX + k, v) for k, v in values.items())]:
        proto.metadata_props.add(key=k, value=v)
    if proto.graph.SerializeToString() != graph:
        raise ExportError(f"{path}: the graph changed while writing its metadata")
    onnx.save(proto, str(path))


def record_envelope(path: str | Path, airframe: AirframeSpec, env: Envelope) -> None:
    """Write `fcemu.airframe` and `fcemu.envelope` into an exported policy's metadata, its graph
    untouched (an export from before they were recorded)."""
    record_metadata(path, {"airframe": airframe.name, "envelope": env.to_json()})
    NeuralRateController(path, airframe=airframe)


def export_policy(target: str | Path, out: str | Path, parity_samples: int = 10_000) -> dict:
    checkpoint = find_checkpoint(target)
    cfg = checkpoint.config
    airframe, env = trained_on(cfg)
    spec = ObservationSpec.from_json(json.dumps(cfg["observation"]))
    model = load_model(checkpoint)
    actor = build_actor(model, checkpoint, spec)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    obs = parity_observations(spec, max(parity_samples, 1), airframe.max_rotor_speed)
    with torch.no_grad():
        expected = actor(torch.as_tensor(obs)).numpy()
        own_error = 0.0
        if actor.flat:  # SB3's feature extractors cast to float32: only the bare MLP runs in float64
            exact = actor.double()(torch.as_tensor(obs, dtype=torch.float64)).numpy()  # and back: exact
            actor.float()
            own_error = float(np.abs(expected - exact).max())
    # A wide input sums hundreds of terms: the float32 network itself is then further than 1e-5
    # from exact arithmetic, and onnxruntime, summing in its own order, lands as far again on
    # the other side: a graph within four times torch's own error computes the same network.
    tolerance = max(PARITY_TOLERANCE, OWN_ERROR_FACTOR * own_error)
    for label, module in graph_modules(actor):
        # The full fold's W'·x and b' = −W'·μ cancel in float32 where μ/σ is large; the
        # centred fold and the unfolded graph subtract μ first.
        normalisation, max_diff = label, _write_graph(module, spec.size, out, obs, expected)
        if max_diff <= tolerance:
            break
    steps = int(getattr(model, "num_timesteps", 0) or cfg.get("trained_steps", 0))  # a checkpoint's own
    metadata = {
        "observation": spec.to_json(),
        "action_mapping": cfg["action_mapping"],
        "throttle": json.dumps(cfg.get("throttle")),
        "loop_rate_hz": str(float(cfg.get("loop_rate_hz", 1000.0))),
        "algorithm": cfg["algo"].lower(),
        "training_steps": str(steps),
        "seed": str(cfg.get("seed")),
        "fcemu_version": __version__,
        "source": str(checkpoint.model_path),
        "parity_max_abs_diff": f"{max_diff:.3e}",
        "parity_samples": str(len(obs)),
        "airframe": airframe.name,
        "envelope": env.to_json(),
    }
    proto = onnx.load(str(out))
    for k, v in metadata.items():
        proto.metadata_props.add(key=META_PREFIX + k, value=v)
    proto.producer_name = "fcemu export"
    onnx.save(proto, str(out))
    NeuralRateController(out, airframe=airframe)  # the firmware must accept it, for its airframe
    report = {"out": str(out), "bytes": out.stat().st_size, "parity_max_abs_diff": max_diff,
              "parity_tolerance": tolerance, "parity_samples": len(obs),
              "parity_ok": max_diff <= tolerance, **{
                  k: metadata[k] for k in ("algorithm", "training_steps", "seed", "action_mapping")},
              "normalisation": normalisation}
    out.with_suffix(".parity.json").write_text(json.dumps(report, indent=2) + "\n")
    if not report["parity_ok"]:
        raise ExportError(f"parity check failed: max |onnx - torch| = {max_diff:.3e} > {tolerance:.3e}")
    return report
