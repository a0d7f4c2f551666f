"""The `fcemu` console script.

Each package owns its subcommands: it registers them here with a cheap
`register(subparsers)` (argparse only) and names its handler as "module:function",
imported only when that subcommand runs, so `fcemu --help` never loads MuJoCo or torch.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from fcemu import __version__

# Packages that contribute commands, in the order `fcemu --help` lists them.
_COMMAND_MODULES = ("firmware.cli", "sim_bridge.cli", "training.cli", "export.cli", "evaluation.cli",
                    "sitl.cli")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fcemu", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"fcemu {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    bench = sub.add_parser("bench", help="throughput and timing-budget figures")
    bench_sub = bench.add_subparsers(dest="bench", required=True, metavar="WHAT")
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue  # that package has no commands
        if hasattr(module, "register"):
            module.register(sub)
        if hasattr(module, "register_bench"):
            module.register_bench(bench_sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    module_name, func_name = args.handler.split(":")
    handler = getattr(importlib.import_module(module_name), func_name)
    try:
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
