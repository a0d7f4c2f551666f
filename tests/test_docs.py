"""The README is a user's guide that stays honest, and the project speaks of itself only.

Every `fcemu …` line in the README's code blocks names a subcommand that exists and options
that its `--help` lists; the cheap ones run. Its Measure table is the one
`python -m fcemu.benchmarks.readme_figures` makes from docs/results/readme_figures.json, whose
figures are those of the results pages they come from. No file of the project names how the work was
organised (an issue or session number) instead of the thing itself.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

from fcemu.benchmarks import readme_figures

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_WORD_BUDGET = 1500
# An issue's or a work session's number: words from how the work was organised, not from the project.
ORGANISATION_WORDS = re.compile(r"\b[Ii]ssues? #?\d+|\b[Ss]essions? \d+")
TEXT_SUFFIXES = {".py", ".md", ".json", ".yaml", ".yml", ".toml", ".txt", ".cfg", ".patch", ".c", ".h"}


def readme_commands() -> list[list[str]]:
    """Each `fcemu …` command of the README, as argv: its fenced blocks' lines (comments
    stripped) and its tables' `fcemu …` cells."""
    text = README.read_text()
    blocks = re.findall(r"^```[a-z]*\n(.*?)^```", text, re.M | re.S)
    lines = [line.split("  #")[0].strip() for block in blocks for line in block.splitlines()]
    lines += re.findall(r"^\|.*?`(fcemu [^`]+)`", text, re.M)
    return [shlex.split(line) for line in lines if line.startswith("fcemu ")]


@cache
@cache
def _help(words: tuple[str, ...]) -> subprocess.CompletedProcess:
    """`fcemu WORDS --help`, once per subcommand: the README names most of them many times."""
    return subprocess.run([sys.executable, "-m", "fcemu", *words, "--help"], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)


def help_text(subcommand: tuple[str, ...]) -> str:
    done = _help(subcommand)
    assert done.returncode == 0, f"fcemu {' '.join(subcommand)} --help: {done.stderr[-500:]}"
    return done.stdout


def subcommand_of(argv: list[str]) -> tuple[str, ...]:
    """The longest run of leading words that is a subcommand: `fcemu bench mcu --json` → ("bench", "mcu")."""
    words: list[str] = []
    for word in argv[1:]:
        if word.startswith("-") or "/" in word or "." in word:
            break
        words.append(word)
    for k in range(len(words), 0, -1):
        done = _help(tuple(words[:k]))
        usage = f"usage: fcemu {' '.join(words[:k])}"
        if done.returncode == 0 and usage in done.stdout:
            return tuple(words[:k])
    return ()


def test_readme_is_within_its_word_budget() -> None:
    words = len(README.read_text().split())
    assert words <= README_WORD_BUDGET, f"README.md has {words} words, the budget is {README_WORD_BUDGET}"


def test_readme_opens_with_the_two_commands() -> None:
    head = README.read_text().splitlines()[:10]
    assert any(line.startswith("make demo") for line in head)
    assert any(line.startswith("make test") for line in head)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_every_readme_command_names_a_real_subcommand_and_real_options() -> None:
    commands = readme_commands()
    assert len(commands) >= 20
    for argv in commands:
        sub = subcommand_of(argv)
        assert sub, f"no subcommand in {' '.join(argv)}"
        text = help_text(sub)
        for option in (w.split("=")[0] for w in argv if w.startswith("--")):
            assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text), \
                f"`{' '.join(argv)}`: fcemu {' '.join(sub)} has no {option}"


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_cheap_readme_commands_run(tmp_path) -> None:
    cheap = [["eval", "--controller", "pid", "--episodes", "3", "--seed", "7", "--json"],
             ["bench", "inference", "--samples", "200", "--json"]]
    listed = {subcommand_of(argv) for argv in readme_commands()}
    for args in cheap:
        assert tuple(args[:2]) in listed or tuple(args[:1]) in listed
        done = subprocess.run([sys.executable, "-m", "fcemu", *args], capture_output=True, text=True,
                              timeout=240, cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-2000:]
        assert isinstance(json.loads(done.stdout), dict)


def test_the_measure_table_is_made_from_the_results_file() -> None:
    figures = readme_figures.load(ROOT)
    readme = README.read_text()
    assert readme_figures.with_table(readme, figures) == readme, \
        "README.md's Measure table is stale: python -m fcemu.benchmarks.readme_figures"
    for figure in figures:
        assert {"figure", "text", "values", "command", "date", "machine"} <= set(figure), figure["figure"]
        assert figure["command"].startswith("fcemu ") and re.fullmatch(r"\d{4}-\d\d-\d\d", figure["date"])
        assert all({"value", "unit"} <= set(value) for value in figure["values"].values()), figure["figure"]


def test_each_figure_is_the_one_its_results_page_gives() -> None:
    figures = readme_figures.load(ROOT)
    assert sum(len(v.get("sources", [])) for f in figures for v in f["values"].values()) >= 6
    # a figure no results page holds is one measured for this table: the exact command run, with --json
    for f in figures:
        if not all(v.get("sources") for v in f["values"].values()):
            assert f.get("made_with", "").startswith("fcemu ") and "--json" in f["made_with"], f["figure"]
    assert readme_figures.source_mismatches(ROOT, figures) == []


def test_the_figures_check_sees_a_figure_its_page_does_not_give() -> None:
    figures = readme_figures.load(ROOT)
    mcu = next(f for f in figures if f["command"] == "fcemu bench mcu")
    mcu["values"]["us"]["value"] = 259.8  # the default before the current one
    found = readme_figures.source_mismatches(ROOT, figures)
    assert len(found) == 2 and all(line.startswith(f"{mcu['figure']}: us in ") for line in found), found


def project_text_files() -> list[Path]:
    listed = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [ROOT / name for name in listed.splitlines()
            if Path(name).suffix in TEXT_SUFFIXES and (ROOT / name).is_file()]


def test_the_project_speaks_of_itself_only() -> None:
    found = []
    for path in project_text_files():
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if ORGANISATION_WORDS.search(line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "name the thing itself:\n" + "\n".join(found[:20])


def test_the_check_sees_organisation_words() -> None:
    issue, session = "issue", "Session"  # apart, so that this file passes its own check
    assert ORGANISATION_WORDS.search(f"meets {issue} 10's bar")
    assert ORGANISATION_WORDS.search(f"({session}s 10 and 11)")
    assert not ORGANISATION_WORDS.search("an InferenceSession 2 times")
    assert not ORGANISATION_WORDS.search("known issues")
