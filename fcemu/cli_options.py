"""The options of every `fcemu` command, and the shared ones side by side (docs/cli.md).

`python -m fcemu.cli_options > docs/cli.md` writes the page; `--counts` prints how many options
each command has and how it spells the shared ones. It reads the parser only: nothing loads.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence

from fcemu.cli import build_parser, shown_option_strings

# The options several commands take, each with one meaning everywhere.
SHARED: dict[str, str] = {
    "--airframe": "the airframe flown or configured: a shipped name (sim_bridge/airframes/NAME.json) "
                  "or a file",
    "--seed": "the seed of what the command draws at random (its help says what: commands, twins, "
              "networks); the same seed draws the same",
    "--episodes": "how many commands (episodes) are flown",
    "--jobs": "worker processes, or torch threads, working in parallel (0: one per CPU this process may use)",
    "--json": "print one JSON object on stdout, the summary the command otherwise prints as text",
    "--out": "where the command writes its files",
}
# Spellings a script may still use for a shared option (accepted, not shown in --help).
FORMER = ("--threads", "--cpus", "--max-minutes")
# A search's wall-clock budget, and a benchmark's or a flight's length: two meanings, two names.
LENGTHS = ("--budget-s", "--tune-budget-s", "--seconds", "--duration")
# Defaults with nothing to show: None and empty (the help says what absence means), SUPPRESS (the
# value comes from elsewhere, e.g. `fcemu sweep --config`).
EMPTY = (None, argparse.SUPPRESS, "", [], (), {})
_DEFAULT = re.compile(r"\(default:? ([^()]*(?:\([^()]*\)[^()]*)*)\)")


def commands(parser: argparse.ArgumentParser | None = None,
             prefix: str = "") -> dict[str, argparse.ArgumentParser]:
    """Every command that runs something ("eval", "bench sim", "twin serve"), by its words."""
    parser = parser or build_parser()
    found: dict[str, argparse.ArgumentParser] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.update(commands(sub, f"{prefix} {name}".strip()))
    if prefix and not found:
        found[prefix] = parser
    return found


def options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The command's options (its positional arguments and --help aside)."""
    return [a for a in parser._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]


def option(parser: argparse.ArgumentParser, name: str) -> argparse.Action | None:
    """The option `name` spells, by its name or by a former spelling."""
    return next((a for a in options(parser) if name in a.option_strings), None)


def rendered_help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """The option's help as `--help` prints it (defaults filled in), on one line."""
    formatter = parser._get_formatter()
    return " ".join(formatter._expand_help(action).split()) if action.help else ""


def is_flag(action: argparse.Action) -> bool:
    return action.nargs == 0 and not isinstance(action, argparse.BooleanOptionalAction)


def shown_default(parser: argparse.ArgumentParser, action: argparse.Action) -> str | None:
    """What the help says the default is: "required", "off" for a flag, else the text of its
    "(default: …)"; None where it says nothing."""
    if action.required:
        return "required"
    if is_flag(action):
        return "off"
    found = _DEFAULT.search(rendered_help(parser, action))
    return found.group(1) if found else None


def problems(parser: argparse.ArgumentParser | None = None) -> list[str]:
    """What breaks the rules: an option without help, a value option (a shared one always) whose
    help shows no default, "(default: None)", a `--json` whose help does not say "one JSON object"."""
    found = []
    for words, sub in commands(parser).items():
        for action in options(sub):
            name = shown_option_strings(action)[0]
            text = rendered_help(sub, action)
            if not text:
                found.append(f"fcemu {words} {name}: no help")
                continue
            if re.search(r"\(default: (None|\[\]|\{\}|\(\)|)\)", text):
                found.append(f"fcemu {words} {name}: the help shows an empty default: {text}")
            value = not is_flag(action) and (name in SHARED or action.default not in EMPTY)
            if value and shown_default(sub, action) is None:
                found.append(f"fcemu {words} {name}: the help shows no default: {text}")
            if name == "--json" and "one JSON object" not in text:
                found.append(f"fcemu {words} --json: the help does not say it prints one JSON object")
    return found


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def markdown(parser: argparse.ArgumentParser | None = None) -> str:
    """docs/cli.md: the shared options, their meaning, and each command's default."""
    found = commands(parser)
    lines = ["# Shared command-line options", "",
             "Generated from the parser by `python -m fcemu.cli_options > docs/cli.md`; "
             "tests/fcemu/test_cli_options.py fails while it is stale.", "",
             "These options mean the same in every command that takes them; `fcemu COMMAND --help` "
             "shows each option's default.", "",
             "| option | meaning |", "|---|---|"]
    lines += [f"| `{name}` | {_cell(meaning)} |" for name, meaning in SHARED.items()]
    lines += ["", "The default per command (`—`: the command has no such option; `off`: a flag, "
              "off unless given):", "",
              "| command | " + " | ".join(f"`{name}`" for name in SHARED) + " |",
              "|---|" + "---|" * len(SHARED)]
    for words, sub in found.items():
        cells = []
        for name in SHARED:
            action = option(sub, name)
            cells.append("—" if action is None else _cell(shown_default(sub, action) or "?"))
        if any(cell != "—" for cell in cells):
            lines.append(f"| `fcemu {words}` | " + " | ".join(cells) + " |")
    lines += ["", "What `--seed` draws, per command:", "", "| command | `--seed` |", "|---|---|"]
    lines += _per_command(found, ("--seed",))
    lines += ["", "Budgets and lengths: `--budget-s` is the wall-clock budget of a search or a race; "
              "`--seconds` and `--duration` are how long a benchmark measures or a flight lasts.", "",
              "| command | option | meaning |", "|---|---|---|"]
    lines += _per_command(found, LENGTHS, named=True)
    former = []
    for words, sub in found.items():
        for spelling in FORMER:
            action = option(sub, spelling)
            if action is not None:
                former.append(f"| `fcemu {words}` | `{spelling}` | `{shown_option_strings(action)[0]}` |")
    if former:
        lines += ["", "Former spellings, still accepted (not shown in `--help`):", "",
                  "| command | spelling | now |", "|---|---|---|", *former]
    return "\n".join(lines) + "\n"


def _per_command(found: dict[str, argparse.ArgumentParser], names: tuple[str, ...],
                 named: bool = False) -> list[str]:
    """A row per command and option of `names` it takes: the option's help, its default kept."""
    rows = []
    for words, sub in found.items():
        for name in names:
            action = option(sub, name)
            if action is not None and shown_option_strings(action)[0] == name:
                cells = [f"`fcemu {words}`", *([f"`{name}`"] if named else []),
                         _cell(rendered_help(sub, action))]
                rows.append("| " + " | ".join(cells) + " |")
    return rows


def counts(parser: argparse.ArgumentParser | None = None) -> str:
    """Per command: its options, and how it spells and describes each shared one."""
    out = []
    for words, sub in commands(parser).items():
        actions = options(sub)
        shared = []
        for name in (*SHARED, *FORMER):
            action = option(sub, name)
            if action is not None and shown_option_strings(action)[0] == name:
                shared.append(name)
        out.append(f"{words:18s} {len(actions):3d} options; shared: {' '.join(shared) or '-'}")
        for name in shared:
            action = option(sub, name)
            assert action is not None
            help_text = rendered_help(sub, action) or "(no help)"
            out.append(f"    {name:12s} default={action.default!r:14s} {help_text[:150]}")
    return "\n".join(out) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fcemu.cli_options", description=__doc__.splitlines()[0])
    parser.add_argument("--counts", action="store_true",
                        help="print each command's option count and shared options instead of docs/cli.md")
    args = parser.parse_args(argv)
    sys.stdout.write(counts() if args.counts else markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
