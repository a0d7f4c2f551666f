"""The README's "Measure" table, made from docs/results/readme_figures.json.

    python -m fcemu.benchmarks.readme_figures            # rewrite the table in README.md
    python -m fcemu.benchmarks.readme_figures --check    # exit 1 where the README or a figure is stale

Each figure in the JSON has its values (each with its unit), the command that measures it, the
date and the machine it was measured on, and where a results page holds the same value, the page
and a pattern whose first group is that value as the page writes it. The table goes between the
README's two markers; `--check` also reads every value back from its pages.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

FIGURES = Path("docs/results/readme_figures.json")
README = Path("README.md")
BEGIN, END = "<!--readme_figures-->", "<!--/readme_figures-->"
HEADER = ("| figure | value | command |", "|---|---|---|")


def load(root: Path) -> list[dict[str, Any]]:
    return json.loads((root / FIGURES).read_text())["figures"]


def cell(figure: dict[str, Any]) -> str:
    """The value column: the figure's template, each `{name}` its value as written in the JSON."""
    values = {name: v["value"] for name, v in figure["values"].items()}
    return figure["text"].format(**values)


def table(figures: list[dict[str, Any]]) -> str:
    rows = [f"| {f['figure']} | {cell(f)} | `{f['command']}` |" for f in figures]
    return "\n".join([*HEADER, *rows])


def with_table(readme: str, figures: list[dict[str, Any]]) -> str:
    """`readme` with the text between its markers replaced by the table."""
    start, stop = readme.index(BEGIN) + len(BEGIN), readme.index(END)
    return readme[:start] + "\n\n" + table(figures) + "\n\n" + readme[stop:]


def number(text: str) -> float:
    return float(text.replace(",", ""))


def source_mismatches(root: Path, figures: list[dict[str, Any]]) -> list[str]:
    """Each value that a results page gives otherwise, or that its pattern no longer finds there."""
    found = []
    for figure in figures:
        for name, value in figure["values"].items():
            for source in value.get("sources", []):
                where = f"{figure['figure']}: {name} in {source['page']}"
                match = re.search(source["pattern"], (root / source["page"]).read_text())
                if match is None:
                    found.append(f"{where}: /{source['pattern']}/ not found")
                elif number(match.group(1)) != float(value["value"]):
                    found.append(f"{where}: {match.group(1)}, the JSON {value['value']}")
    return found


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fcemu.benchmarks.readme_figures",
                                description="The README's Measure table, made from " + str(FIGURES))
    p.add_argument("--root", type=Path, default=Path.cwd(), help="the checkout (default: here)")
    p.add_argument("--check", action="store_true", help="change nothing: exit 1 where anything is stale")
    args = p.parse_args(argv)
    figures = load(args.root)
    readme = (args.root / README).read_text()
    made = with_table(readme, figures)
    stale = source_mismatches(args.root, figures)
    if args.check:
        if made != readme:
            stale.insert(0, f"{README}: its table is not the one {FIGURES} makes (run without --check)")
        for line in stale:
            print(line, file=sys.stderr)
        return 1 if stale else 0
    if made != readme:
        (args.root / README).write_text(made)
        print(f"wrote the table of {len(figures)} figures into {README}", file=sys.stderr)
    for line in stale:
        print(f"stale: {line}", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
