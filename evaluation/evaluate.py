"""What `fcemu eval` does: fly each controller over the same commands, score, report."""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from fcemu.evaluation import faults as fault_eval
from fcemu.evaluation.metrics import AXES, EvalMetrics, compute_metrics
from fcemu.evaluation.perturb import PerturbedAirframe, PerturbedResult, fly_perturbed, perturbed_airframes
from fcemu.evaluation.report import ControllerResult, write_report
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.controllers import is_policy, resolve
from fcemu.sim_bridge.randomization import RandomizationError, ranges_for
from fcemu.sitl.traces import Traces, save_traces

REPORT_CONTINUOUS_S = 10.0


def result_json(spec: str, cfg: EvalConfig, metrics: EvalMetrics,
                perturbed: PerturbedResult | None = None) -> dict:
    out = {"controller": spec, "episodes": cfg.episodes, "seed": cfg.seed, "task": cfg.task,
           "airframe": cfg.airframe, "metrics": metrics.to_json(), "details": metrics.details_json()}
    if cfg.twin is not None:
        out["twin"] = cfg.twin
    if perturbed is not None:
        out["perturbed"] = perturbed.metrics.to_json()
        out["perturbation"] = perturbed.details_json()
    return out


def traces_path(base: str, spec: str, several: bool) -> Path:
    path = Path(base)
    if not several:
        return path
    slug = Path(spec).stem if spec.endswith(".onnx") else spec.replace(":", "_")
    return path.with_name(f"{path.stem}_{slug}{path.suffix or '.npz'}")


def summary_line(spec: str, m: EvalMetrics) -> str:
    def cell(metric: str) -> str:
        return "/".join(_fmt(m.stat(metric, a).mean) for a in AXES)

    total = sum(m.stat("error", a).mean for a in AXES)
    return (f"{spec:>28}  rise ms {cell('rise_ms')}  peak % {cell('peak_pct')}  error {cell('error')} "
            f"(sum {total:.1f})  success % {cell('success_pct')}  smoothness {cell('smoothness')}")


def _fmt(x: float | None) -> str:
    return "n/a" if x is None or x != x else f"{x:.1f}"


def _airframes(args) -> tuple[list[PerturbedAirframe], str | None]:
    """The perturbed airframes and the path of the ranges they were drawn from (none without --perturb)."""
    only = getattr(args, "perturb_only", None)
    if not args.perturb:
        if only is not None:
            raise ValueError("--perturb-only picks among the airframes --perturb N draws: give --perturb")
        return [], None
    ranges = ranges_for(args.airframe, args.ranges)  # drawn around --airframe: its own, or relative ones
    drawn = perturbed_airframes(ranges, args.perturb, args.perturb_seed)
    if only is None:
        return drawn, str(ranges.path)
    if any(not 0 <= i < len(drawn) for i in only) or len(set(only)) != len(only):
        raise ValueError(f"--perturb-only picks airframes of the --perturb {args.perturb} drawn, each once "
                         f"by its index 0..{args.perturb - 1}; got {' '.join(map(str, only))}")
    return [drawn[i] for i in only], str(ranges.path)


def fallback_for(airframe: str, fallback: str | None, controllers: list[str]) -> str:
    """The PID a policy hands over to (`firmware.controllers.resolve_fallback`): `fallback` where given,
    else the one a policy names, else the airframe's own tune, or where none is shipped, the one PID
    preset flown beside the policy (`--controller pid:DIR/pid.json`)."""
    from fcemu.firmware.controllers import resolve_fallback
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    return resolve_fallback(fallback, controllers, lambda: airframe_spec(airframe))


def eval_command(args) -> int:
    specs = args.controller or ["pid"]
    try:
        cfg = EvalConfig(task=args.task, episodes=args.episodes, seed=args.seed, episode_s=args.episode_s,
                         throttle=args.throttle, airframe=args.airframe,
                         fallback=fallback_for(args.airframe, args.fallback, specs), twin=args.twin)
        if args.perturb < 0:
            raise ValueError(f"--perturb must be >= 0, got {args.perturb}")
        if args.twin is not None and args.perturb:
            raise ValueError("--twin flies one given airframe: it does not combine with --perturb")
        airframes, ranges = _airframes(args)
        faults = fault_eval.check_specs(getattr(args, "fault", None) or [])
    except (RandomizationError, ValueError) as exc:
        print(f"fcemu: error: {exc}", file=sys.stderr)
        return 2
    progress = sys.stderr.isatty()
    bar = tqdm(total=len(specs) * len(airframes), desc="perturbed airframes", unit="airframe",
               disable=not (progress and airframes), leave=False)
    results: list[ControllerResult] = []
    payload = []
    for spec in specs:
        traces = run_controller(spec, cfg, progress=progress)
        metrics = compute_metrics(traces)
        perturbed = None
        if airframes:
            bar.set_postfix_str(spec)
            perturbed = fly_perturbed(spec, cfg, airframes, args.perturb_seed,
                                      on_airframe=lambda _: bar.update(), ranges=ranges)
        payload.append(result_json(spec, cfg, metrics, perturbed))
        fault_rows = [_fly_fault(spec, cfg, fault, traces, progress) for fault in faults]
        if fault_rows:
            payload[-1]["faults"] = [r.to_json() for r in fault_rows]
        if args.save_traces:
            out = save_traces(traces_path(args.save_traces, spec, len(specs) > 1), traces)
            print(f"traces: {out}", file=sys.stderr)
        continuous = traces if cfg.task == "continuous" else None
        if args.report and continuous is None:
            trace_cfg = replace(cfg, task="continuous", episodes=1, episode_s=REPORT_CONTINUOUS_S)
            continuous = run_controller(spec, trace_cfg, progress=False)
        step = traces.step_window() if cfg.task != "continuous" else None
        results.append(ControllerResult(spec, metrics, step, _first(continuous), perturbed,
                                        tuple(fault_rows)))
        if not args.json:
            print(summary_line(spec, metrics))
            for r in fault_rows:
                print(fault_eval.summary_line(spec, r))
            if perturbed is not None:
                print(summary_line(f"perturbed x{len(airframes)}", perturbed.metrics))
    bar.close()
    if args.report:
        command = "fcemu " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        md = write_report(args.report, results, command=command, seed=cfg.seed, task=cfg.task,
                          episodes=cfg.episodes, airframe=cfg.airframe, twin=cfg.twin)
        print(f"report: {md}", file=sys.stderr)
    if args.json:
        print(json.dumps(payload[0] if len(payload) == 1 else {"results": payload}))
    return 0


def _fly_fault(spec: str, cfg: EvalConfig, fault, nominal: Traces, progress: bool) -> fault_eval.FaultResult:
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    plan = fault_eval.FaultPlan(fault, cfg.seed, cfg.episodes, cfg.n_ticks, cfg.warmup_ticks)
    faulted = run_controller(spec, cfg, progress=progress, faults=plan)
    flown = resolve(spec, airframe_spec(cfg.airframe))
    return fault_eval.fault_result(plan, faulted, nominal, 1.0 / cfg.rate_hz, policy=is_policy(flown))


def _first(traces: Traces | None) -> Traces | None:
    return None if traces is None else traces.episode(0)
