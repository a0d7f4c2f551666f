"""Shared options have one name, one meaning and a shown default in every command; docs/cli.md is
the parser's own table of them (`python -m fcemu.cli_options > docs/cli.md`)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from fcemu.cli import _Parser, build_parser
from fcemu.cli_options import SHARED, commands, markdown, option, problems, shown_default

pytestmark = pytest.mark.no_wall_clock

ROOT = Path(__file__).resolve().parents[2]


def test_docs_cli_md_is_the_parser_s_table() -> None:
    assert (ROOT / "docs" / "cli.md").read_text() == markdown(), \
        "docs/cli.md is stale: python -m fcemu.cli_options > docs/cli.md"


def test_every_option_has_help_and_every_value_option_shows_its_default() -> None:
    assert problems() == []


def test_every_shared_option_has_its_help_and_its_default_in_every_command() -> None:
    found = commands()
    taken = {name: [words for words, sub in found.items() if option(sub, name)] for name in SHARED}
    assert all(len(where) >= 2 for where in taken.values()), taken  # shared: by more than one command
    for words, sub in found.items():
        for name in SHARED:
            action = option(sub, name)
            if action is not None:
                assert action.help, f"fcemu {words} {name}"
                assert shown_default(sub, action), f"fcemu {words} {name}: {action.help}"
    assert set(taken["--json"]) >= {"sitl", "twin serve", "twin demo", "eval"}


def _bad_parser(help_text: str | None, default: object) -> argparse.ArgumentParser:
    parser = _Parser(prog="fcemu")
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("x")
    p.add_argument("--seed", type=int, default=default, help=help_text)
    p.add_argument("--json", action="store_true", help="print it")
    return parser


def test_the_checks_see_a_missing_help_an_unshown_default_and_a_json_without_its_object() -> None:
    json_problem = "fcemu x --json: the help does not say it prints one JSON object"
    assert problems(_bad_parser(None, 0)) == ["fcemu x --seed: no help", json_problem]
    assert problems(_bad_parser("the seed", None))[0].startswith("fcemu x --seed: the help shows no default")
    assert problems(_bad_parser("the seed", 3)) == [json_problem]  # the formatter shows "(default: 3)"
    shown = commands(_bad_parser("the seed", 3))["x"].format_help()
    assert "the seed (default: 3)" in " ".join(shown.split())


def test_the_help_shows_no_empty_default() -> None:
    for words, sub in commands().items():
        assert not re.search(r"\(default: (None|\[\]|\{\}|)\)", sub.format_help()), words


@pytest.mark.parametrize(("argv", "dest", "value"), [
    (["train", "--jobs", "3"], "threads", 3),
    (["train", "--threads", "3"], "threads", 3),
    (["distill", "x.onnx", "--threads", "2"], "threads", 2),
    (["bench", "train", "--jobs", "2"], "threads", 2),
    (["sweep", "--jobs", "2"], "cpus", 2),
    (["sweep", "--cpus", "2"], "cpus", 2),
    (["bench", "train", "--budget-s", "90"], "budget_s", 90.0),
    (["bench", "train", "--max-minutes", "1.5"], "budget_s", 90.0),
    (["bench", "train"], "budget_s", 900.0),
])
def test_former_spellings_still_work(argv: list[str], dest: str, value: object) -> None:
    assert getattr(build_parser().parse_args(argv), dest) == value


def test_former_spellings_are_not_shown() -> None:
    found = commands()
    for words, former in (("train", "--threads"), ("distill", "--threads"), ("bench train", "--threads"),
                          ("sweep", "--cpus"), ("bench train", "--max-minutes")):
        assert option(found[words], former) is not None
        assert not re.search(rf"(?<![\w-]){former}(?![\w-])", found[words].format_help()), (words, former)
