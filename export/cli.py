"""`fcemu export` (checkpoint → ONNX, or ONNX policy → C) and `fcemu bench mcu`."""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="checkpoint → ONNX with metadata and a parity check; "
                                      "--target c: ONNX policy → C99 sources with host parity; "
                                      "--target betaflight: Betaflight 4.6 with the policy as NEURAL mode")
    p.add_argument("checkpoint", help="a run directory (runs/NAME) or a checkpoint .zip in it; "
                                      "with --target c, a policy .onnx")
    p.add_argument("--out", required=True, help="the .onnx file to write (--target c: a directory)")
    p.add_argument("--target", choices=("onnx", "c", "betaflight"), default="onnx",
                   help="onnx: a checkpoint to ONNX; c: an ONNX policy to C99 sources; betaflight: "
                        "Betaflight with the policy built in")
    p.add_argument("--betaflight-targets", default="SITL,STM32F405,STM32H743", metavar="T1,T2",
                   help="--target betaflight: what to build (SITL, STM32F405, STM32H743)")
    p.add_argument("--parity-samples", type=int, default=10_000,
                   help="observations the export's outputs are checked on against its source's")
    _add_tanh(p)
    p.add_argument("--json", action="store_true", help="print the report as one JSON object on stdout")
    p.set_defaults(handler="fcemu.export.cli:export_command")


def _add_tanh(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tanh", choices=("fast", "libm"), default="fast",
                   help="--target c: the network's tanh, a rational approximation within 7 ULP "
                        "(fast) or libm's tanhf")


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("mcu", help="the policy as C on a Cortex-M4F under QEMU: parity, size, "
                                         "instructions and estimated time per inference")
    p.add_argument("--model", default=None, help="a policy .onnx (default: the shipped policy)")
    p.add_argument("--out", default=None, help="keep the exported sources and the firmware image here "
                                               "(default: none; built in a temporary folder)")
    _add_tanh(p)
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object on stdout")
    p.set_defaults(handler="fcemu.export.cli:bench_mcu_command")


def _error(exc: Exception) -> int:
    print(f"fcemu: error: {exc}", file=sys.stderr)
    return 2


def _print_report(args, report: dict, summary: str) -> int:
    """The report as one JSON line with --json, else the one-line summary."""
    print(json.dumps(report) if args.json else summary)
    return 0


def export_command(args) -> int:
    if getattr(args, "target", "onnx") == "c":
        return _export_c(args)
    if getattr(args, "target", "onnx") == "betaflight":
        return _export_betaflight(args)
    from fcemu.export.onnx_export import ExportError, export_policy

    try:
        report = export_policy(args.checkpoint, args.out, args.parity_samples)
    except (ExportError, FileNotFoundError) as exc:
        return _error(exc)
    return _print_report(args, report,
                         f"wrote {report['out']} ({report['bytes']} bytes, {report['algorithm']}, "
                         f"{report['training_steps']} steps); parity over {report['parity_samples']} "
                         f"observations: max |onnx − torch| = {report['parity_max_abs_diff']:.2e} "
                         "(≤ 1e-5: ok)")


def _export_c(args) -> int:
    from fcemu.export.c.build import CExportError, export_c

    try:
        report = export_c(args.checkpoint, args.out, args.parity_samples, args.tanh)
    except CExportError as exc:
        return _error(exc)
    return _print_report(args, report,
                         f"wrote C99 sources and {report['out']}/libfcemu_policy.so; parity with onnxruntime "
                         f"over {report['parity_samples']} observations: max |c − onnx| = "
                         f"{report['max_abs_diff']:.2e}, max {report['max_ulp']} ULP "
                         f"(figures in {report['out']}/parity.json)")


def _export_betaflight(args) -> int:
    from fcemu.export.betaflight.build import BetaflightExportError, export_betaflight
    from fcemu.export.c.build import CExportError

    targets = [t.strip() for t in args.betaflight_targets.split(",") if t.strip()]
    try:
        report = export_betaflight(args.checkpoint, args.out, targets, args.tanh, args.parity_samples,
                                   progress=lambda line: print(f"[betaflight] {line}", file=sys.stderr))
    except (BetaflightExportError, CExportError) as exc:
        return _error(exc)
    sizes = "; ".join(f"{t}: flash {s['flash_bytes']} B ({s['flash_pct']} %), RAM {s['ram_bytes']} B "
                      f"({s['ram_pct']} %)" for t, s in report["size"].items())
    return _print_report(args, report, f"wrote Betaflight {report['betaflight']} with NEURAL (aux mode id "
                                       f"{report['neural_box_permanent_id']}) to {args.out}: built "
                                       f"{', '.join(report['builds'])}" + (f"; {sizes}" if sizes else ""))


def bench_mcu_command(args) -> int:
    from fcemu.export.c.build import CExportError
    from fcemu.export.c.target import REPORT_KEYS, bench_mcu, budget_verdict

    try:
        details = bench_mcu(args.model, args.out, tanh=args.tanh)
    except CExportError as exc:
        return _error(exc)
    report = {k: details[k] for k in REPORT_KEYS}
    if args.json:
        print(json.dumps(report))
        return 0
    for key, value in report.items():
        print(f"{key:28s} {value}")
    host, target = details["host"], details["target"]
    print(f"host C vs onnxruntime ({host['parity_samples']} observations): max |diff| "
          f"{host['max_abs_diff']:.2e}, {host['max_ulp']} ULP")
    print(f"Cortex-M4F in QEMU vs onnxruntime ({target['vectors']} observations): max |diff| "
          f"{target['max_abs_diff_vs_onnx']:.2e}, {target['max_ulp_vs_onnx']} ULP; vs host C: "
          f"{target['max_abs_diff_vs_host']:.2e}, {target['max_ulp_vs_host']} ULP")
    cycles = details["cycles"]
    print(f"RAM = {target['static_ram_bytes']} static + {target['stack_bytes']} stack (painted); "
          f"tanh: {details['tanh']}")
    print(f"cycles: {cycles['instructions']} instructions traced → {cycles['cycles']} by the Cortex-M4 "
          f"TRM tables (band {cycles['cycles_low']}–{cycles['cycles_high']}) + {cycles['art_wait_cycles']} "
          f"flash wait behind the F405's ART = {report['est_cycles']}: {report['est_us_at_168mhz']} µs at "
          f"168 MHz")
    print(f"  every taken branch and weight line waiting on flash: {report['est_us_at_168mhz_flash_bound']} "
          f"µs; instructions × CPI {details['cpi_assumed']}: {report['est_us_at_168mhz_cpi']} µs")
    print(budget_verdict(report))
    return 0
