"""Tune the rate PID for an airframe from a checkout: `fcemu tune`, runnable as a script.

    .venv/bin/python benchmarks/tune_pid.py --airframe iris --out runs/tune_iris --json

The search lives in `fcemu.training.pid_tune` (the physics start, the stages, the held-out
check against `fcemu bound`) and `fcemu.training.pid_search` (flights and the pattern
search). `firmware/presets/pid_iris.json` was made by this script's earlier, Iris-only
version (its description and "tuning" record keep the settings; git history has the code:
commit 297ccbc and before); `fcemu tune --airframe iris` starts from that preset.
"""

from __future__ import annotations

import argparse
import sys

from fcemu.firmware.errors import UserError
from fcemu.training.cli import register_tune
from fcemu.training.pid_tune_cli import tune_command


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tune_pid.py")
    register_tune(parser.add_subparsers())
    args = parser.parse_args(["tune", *(sys.argv[1:] if argv is None else argv)])
    try:
        return tune_command(args)
    except UserError as exc:
        print(f"tune_pid.py: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
