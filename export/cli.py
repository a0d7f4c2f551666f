"""`fcemu export`."""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="checkpoint → ONNX with metadata and a parity check")
    p.add_argument("checkpoint", help="a run directory (runs/NAME) or a checkpoint .zip in it")
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--parity-samples", type=int, default=10_000)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler="export.cli:export_command")


def export_command(args) -> int:
    from export.onnx_export import ExportError, export_policy

    try:
        report = export_policy(args.checkpoint, args.out, args.parity_samples)
    except (ExportError, FileNotFoundError) as exc:
        print(f"fcemu export: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report))
    else:
        print(f"wrote {report['out']} ({report['bytes']} bytes, {report['algorithm']}, "
              f"{report['training_steps']} steps); parity over {report['parity_samples']} observations: "
              f"max |onnx − torch| = {report['parity_max_abs_diff']:.2e} (≤ 1e-5: ok)")
    return 0
