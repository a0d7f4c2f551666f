"""`fcemu sweep`: many `fcemu train` runs over seeds and settings on Ray Tune, top to bottom.

spec (seeds × search space, `fcemu train` options; command line over YAML) → Ray, local or
joined with --address → one Tune trial per point, each `training.train.train(cfg)` with
its in-training race against the PID reported to Tune → ASHA stops trials whose best Error
ratio falls behind → (--perturb N: each trial's policy flown on N perturbed airframes, the
PID once after them) → results table (CSV, Markdown) → the best trial's policy exported to
OUT/best/policy.onnx and flown through the firmware loop against the PID.

Layout: OUT/sweep.json (the spec), OUT/ray/ (Tune's experiment: restored when the same
sweep is run again after an interruption), OUT/runs/<trial>/ (each a `fcemu train` run
directory), OUT/results.csv, OUT/results.md, OUT/best/ (policy.onnx, eval.json, report/).
On a cluster OUT must be storage every node sees, as Tune's storage path must be.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import itertools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME
from fcemu.training import sweep_perturbed
from fcemu.training.config import FIELDS, TrainConfig
from fcemu.training.sweep_results import METRIC, trial_rows, write_tables

EXPERIMENT = "sweep"


class SweepError(RuntimeError):
    """Ray or the trials failed: `fcemu: error: ...`, exit status 1."""


# ── 1. The specification: seeds × search space, on top of `fcemu train` options ──────
def parse_seeds(text: str | int | list[int]) -> list[int]:
    """`0-4`, `0,2,5`, `0-2,7` (or a YAML list) → sorted distinct seeds."""
    if isinstance(text, int):
        return [text]
    if isinstance(text, list):
        return sorted({int(s) for s in text})
    seeds: set[int] = set()
    for part in str(text).split(","):
        lo, dash, hi = part.strip().partition("-")
        try:
            seeds.update(range(int(lo), int(hi) + 1) if dash else [int(lo)])
        except ValueError:
            raise ValueError(f"--seeds {text!r}: expected e.g. 0-4 or 0,2,5") from None
    if not seeds:
        raise ValueError(f"--seeds {text!r}: no seeds")
    return sorted(seeds)


def _literal(text: str) -> Any:
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_space(items: list[str]) -> dict[str, list[Any]]:
    """`key=v1,v2` → {key: [v1, v2]}; a value that is one literal (`[64, 64]`) is one point."""
    space: dict[str, list[Any]] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key or not text:
            raise ValueError(f"--hp {item!r}: expected key=value[,value...]")
        value = _literal(text)
        if isinstance(value, str) and "," in text:
            value = tuple(_literal(v) for v in text.split(","))
        space[key] = list(value) if isinstance(value, tuple) else [value]
    return space


@dataclasses.dataclass
class SweepSpec:
    seeds: list[int]
    space: dict[str, list[Any]]  # TrainConfig field or algorithm hyper-parameter → values tried
    train: dict[str, Any]  # fixed `fcemu train` options (TrainConfig fields)
    # Each trial's policy flown on perturbed airframes after training (empty: not flown):
    # {"airframes": N, "seed": S, "episodes": E, "ranges": name or file}
    perturb: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def n_trials(self) -> int:
        n = len(self.seeds)
        for values in self.space.values():
            n *= len(values)
        return n

    def config(self, seed: int, settings: dict[str, Any], out: str, threads: int) -> TrainConfig:
        """The trial's `fcemu train` configuration: settings naming a TrainConfig field set it,
        the others are algorithm hyper-parameters."""
        fields = {k: v for k, v in settings.items() if k in FIELDS}
        hp = {**self.train.get("hp", {}), **{k: v for k, v in settings.items() if k not in FIELDS}}
        return TrainConfig(**{**self.train, **fields, "hp": hp, "seed": seed, "out": out,
                              "threads": threads, "progress": False})


def spec_from_args(args, defaults: dict[str, Any]) -> SweepSpec:
    """Defaults < YAML file < what the command line gives."""
    data: dict[str, Any] = {}
    if args.config:
        import yaml

        try:
            data = yaml.safe_load(Path(args.config).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ValueError(f"--config {args.config}: {exc}") from None
        if not isinstance(data, dict):
            raise ValueError(f"--config {args.config}: expected a mapping")
    seeds = parse_seeds(args.seeds if args.seeds is not None else data.pop("seeds", 0))
    data.pop("seeds", None)
    space = data.pop("space", None) or {}
    if not isinstance(space, dict):
        raise ValueError(f"--config {args.config}: space must map options to lists of values")
    space = {k: v if isinstance(v, list) else [v] for k, v in space.items()}
    space.update(parse_space(args.hp))
    unknown = sorted(set(data) - set(FIELDS))
    if unknown:
        raise ValueError(f"--config {args.config}: unknown options {unknown}")
    for key in ("seed", "out"):
        if key in space or key in data:
            raise ValueError(f"{key} is the sweep's own (--seeds, --out)")
    given = {k: getattr(args, k) for k in FIELDS if hasattr(args, k) and k != "hp"}  # --hp: the space
    train = {**defaults, **data, **given}
    cfg = TrainConfig(**train)  # validates the fixed options
    if not 0 < cfg.eval_every <= cfg.steps:
        raise ValueError("a sweep needs 0 < --eval-every <= --steps: early stopping and the choice "
                         "of the best trial read the in-training evaluations")
    spec = SweepSpec(seeds, space, {k: v for k, v in dataclasses.asdict(cfg).items()
                                    if k not in ("seed", "out", "threads", "progress")},
                     sweep_perturbed.perturb_from_args(args, cfg))
    for point in itertools.product(*space.values()):  # a bad value fails here, not in a trial
        spec.config(seeds[0], dict(zip(space, point, strict=True)), "unused", threads=1)
    return spec


# ── 2. One trial: one `fcemu train` run, its race against the PID reported to Tune ─────
def _race_reporting_to_tune(cfg: TrainConfig):
    from ray import tune

    from fcemu.training.train import PidRaceCallback

    class TuneRace(PidRaceCallback):
        """The in-training race; each evaluation goes to Tune, which may stop the trial there."""

        def _on_step(self) -> bool:
            n = len(self.history)
            keep_going = super()._on_step()
            if len(self.history) > n and self.num_timesteps < self.cfg.steps:  # the last: in the final report
                tune.report(trial_metrics(self.history, self.best))
            return keep_going

    return TuneRace(cfg, cfg.eval_every)


def trial_metrics(history: list[dict[str, Any]], best_path: Path | None) -> dict[str, Any]:
    """What a trial reports: the last evaluation, and the best so far: the one the race
    exports (`quick_eval.selection_key`: meeting the deployable bar first, then the Error ratio
    with a penalty for roughness beyond it), so a row's figures are its exported policy's."""
    best = min(history, key=lambda h: tuple(h["selection_key"]))
    return {"error_ratio": history[-1]["error_ratio"], METRIC: best["error_ratio"],
            "best_steps": best["steps"], "success_pct": list(best["success_pct"].values()),
            "smoothness": best["smoothness"], "meets_bar": bool(best["meets_bar"]),
            "selection_key": list(best["selection_key"]), "steps": history[-1]["steps"],
            "wall_s": history[-1]["wall_s"], "best_checkpoint": str(best_path) if best_path else None,
            "finished": False}


def run_trial(point: dict[str, Any], spec: dict[str, Any], runs: str, threads: int) -> None:
    from ray import tune

    from fcemu.training.train import train

    trial = tune.get_context().get_trial_id()
    cfg = SweepSpec(**spec).config(point["seed"], point["settings"], str(Path(runs) / trial), threads)
    race = _race_reporting_to_tune(cfg)
    summary = train(cfg, race=race)
    final = trial_metrics(race.history, race.best)
    final.update(finished=True, steps=summary["steps"], wall_s=summary["train_wall_s"],
                 steps_per_s=summary["steps_per_s"], exported=summary["exported"])
    if spec["perturb"]:
        final["perturbed"] = sweep_perturbed.fly_summary(summary["export"]["out"], spec["perturb"])
    tune.report(final)


# ── 3. Ray Tune: start or join Ray, grid over the space, ASHA, restore ────────────────
def tune_sweep(spec: SweepSpec, out: Path, args) -> Any:
    """Ray started or joined; a Tuner over the grid, or the interrupted one restored."""
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # the classic reporter: a table on stderr
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    # Ray nices its workers (15) to keep its own daemons responsive; here the trials are the
    # work, and niced they starve behind any other job on a shared machine.
    os.environ.setdefault("RAY_worker_niceness", "0")
    import logging

    import ray
    from ray import tune
    from ray.tune.schedulers import ASHAScheduler, FIFOScheduler

    for attempt in range(3):  # a local Ray gives its raylet a fixed 30 s, short on a loaded machine
        try:
            if args.address:
                ray.init(address=args.address, logging_level=logging.ERROR)
            else:
                ray.init(num_cpus=args.cpus, include_dashboard=False, logging_level=logging.ERROR)
            break
        except Exception as exc:  # Ray's start-up failures include a bare Exception
            ray.shutdown()
            if args.address or attempt == 2:
                where = f" at {args.address}" if args.address else ""
                raise SweepError(f"Ray did not start{where}: {exc}") from None
            print(f"fcemu sweep: Ray did not start ({exc}); trying again", file=sys.stderr)

    gpus = args.gpus_per_trial or 0
    trainable = tune.with_resources(
        tune.with_parameters(run_trial, spec=dataclasses.asdict(spec), runs=str((out / "runs").resolve()),
                             threads=args.cpus_per_trial),
        {"cpu": args.cpus_per_trial, "gpu": gpus})
    storage = str((out / "ray").resolve())
    path = os.path.join(storage, EXPERIMENT)
    if tune.Tuner.can_restore(path):
        print(f"fcemu sweep: resuming the sweep in {out}", file=sys.stderr)
        return tune.Tuner.restore(path, trainable, resume_unfinished=True, restart_errored=True)

    evals = max(1, spec.train["steps"] // spec.train["eval_every"])
    if args.no_early_stop:
        scheduler = FIFOScheduler()
    else:  # reports: the evaluations before the end, then the final one (after the export)
        scheduler = ASHAScheduler(time_attr="training_iteration", max_t=evals + 1,
                                  grace_period=args.grace or max(1, evals // 4), reduction_factor=2)
    reporter = tune.CLIReporter(
        metric_columns={METRIC: "best ratio", "error_ratio": "ratio", "steps": "steps", "wall_s": "s"},
        parameter_columns={"seed": "seed", **{f"settings/{k}": k for k in spec.space}},
        max_report_frequency=10, sort_by_metric=True)
    param_space = {"seed": tune.grid_search(spec.seeds),
                   "settings": {k: tune.grid_search(v) for k, v in spec.space.items()}}
    tuner = tune.Tuner(
        trainable, param_space=param_space,
        tune_config=tune.TuneConfig(metric=METRIC, mode="min", scheduler=scheduler),
        run_config=tune.RunConfig(name=EXPERIMENT, storage_path=storage, progress_reporter=reporter,
                                  verbose=1))
    return tuner


def _second_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def fit(tuner) -> tuple[Any, bool]:
    """Tune's results, and whether Ctrl-C ended the run (its state saved for a resume).

    On the first SIGINT Tune saves the experiment, ends the run and puts back the handler it
    found: ours, which makes a second Ctrl-C a plain KeyboardInterrupt and tells us it happened.
    """
    import signal

    previous = signal.signal(signal.SIGINT, _second_interrupt)
    try:
        results = tuner.fit()
        return results, signal.getsignal(signal.SIGINT) is _second_interrupt
    finally:
        signal.signal(signal.SIGINT, previous)


# ── 4. Results: the best policy flown in the firmware (the table: `sweep_results`) ─────
def export_best(rows: list[dict[str, Any]], spec: SweepSpec, out: Path, episodes: int) -> dict[str, Any]:
    """The best trial's exported checkpoint → OUT/best/policy.onnx, flown against the PID; trials
    rank as the race ranks evaluations (`quick_eval.selection_key`)."""
    from fcemu.export.onnx_export import export_policy
    from fcemu.training.train import evaluate_run

    ranked = [r for r in rows if r["best_error_ratio"] is not None and r["best_checkpoint"]]
    if not ranked:
        raise SweepError("no trial reached an in-training evaluation; nothing to export "
                         f"(the trials' errors: {out / 'ray' / EXPERIMENT})")
    best = min(ranked, key=lambda r: tuple(r["selection_key"] or (1, r["best_error_ratio"])))
    (out / "best").mkdir(parents=True, exist_ok=True)
    export = export_policy(best["best_checkpoint"], out / "best" / "policy.onnx")
    result: dict[str, Any] = {**best, "policy": str(out / "best" / "policy.onnx"), "export": export}
    if episodes:
        cfg = spec.config(best["seed"], best["settings"], str(out / "best"), threads=1)
        cfg.eval_episodes = episodes
        payload = evaluate_run(out / "best", cfg)
        result["eval"] = {"episodes": episodes, "seed": cfg.eval_seed, "bar": payload["bar"]}
    return result


# ── 5. The command ────────────────────────────────────────────────────────────────────
@contextlib.contextmanager
def stdout_to_stderr():
    """Ray and Tune's reporter write to stdout: send fd 1 to stderr, so with --json the one
    JSON object is all stdout carries."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def saved_spec(raw: dict[str, Any], spec: SweepSpec) -> dict[str, Any]:
    """A saved sweep's spec as this version writes it: one saved before --perturb existed has no
    "perturb" (the same as not flying them), one saved before an option existed lacks it (the
    same as its default, where this sweep leaves it there)."""
    train = raw.get("train", {})
    added = {k: v for k, v in spec.train.items() if k not in train and k in FIELDS and v == FIELDS[k].default}
    perturb = raw.get("perturb") or {}
    if perturb:  # one saved before it named the airframe flew the default
        perturb = {"airframe": DEFAULT_AIRFRAME, **perturb}
    return {**raw, "perturb": perturb, "train": {**added, **train}}


def sweep_command(args) -> int:
    from fcemu.firmware.errors import UserError
    from fcemu.training.cli import SWEEP_DEFAULTS

    out = Path(args.out or "runs/sweep")
    try:
        spec = spec_from_args(args, SWEEP_DEFAULTS)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    saved = out / "sweep.json"
    stored = json.dumps(dataclasses.asdict(spec), sort_keys=True, default=list)
    if saved.is_file() and json.dumps(saved_spec(json.loads(saved.read_text()), spec),
                                      sort_keys=True, default=list) != stored:
        raise UserError(f"{out} holds a different sweep (its spec: {saved}); choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps(dataclasses.asdict(spec), indent=2, default=list) + "\n")

    try:
        with stdout_to_stderr():
            payload = run_sweep(spec, out, args)
    except SweepError as exc:
        print(f"fcemu: error: {exc}", file=sys.stderr)
        return 1
    if payload is None:
        print(f"fcemu sweep: interrupted; the same command resumes it from {out}", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(payload, default=str))
        return 0
    print((out / "results.md").read_text(), end="")
    best = payload["best"]
    bar = best.get("eval", {}).get("bar")
    verdict = "" if bar is None else f"; flown: Error ×{bar['error_ratio']:.3f} vs {bar['best_pid']}"
    print(f"best: trial {best['trial']} (seed {best['seed']}) ×{best['best_error_ratio']:.3f} in training"
          f"{verdict}; policy {best['policy']}")
    return 0


def run_sweep(spec: SweepSpec, out: Path, args) -> dict[str, Any] | None:
    """The sweep's JSON payload; None when Ctrl-C interrupted it."""
    import ray

    t0 = time.perf_counter()
    print(f"fcemu sweep: {spec.n_trials} trials ({len(spec.seeds)} seeds × "
          f"{spec.n_trials // len(spec.seeds)} settings) of {spec.train['steps']} steps", file=sys.stderr)
    try:
        results, interrupted = fit(tune_sweep(spec, out, args))
        if interrupted:
            return None
        rows = trial_rows(results)
        pid = sweep_perturbed.judge(rows, spec.perturb) if spec.perturb else None
        write_tables(rows, out, perturbed=pid is not None)
        best = export_best(rows, spec, out, args.best_episodes)
    finally:
        ray.shutdown()
    payload = {"engine": "ray", "ray_version": ray.__version__, "out": str(out), "steps": spec.train["steps"],
               "wall_s": round(time.perf_counter() - t0, 1), "trials": rows, "best": best}
    if pid is not None:
        payload["perturbed_pid"] = {**spec.perturb, **pid}
    return payload
