"""`fcemu sweep`'s results: a row per Tune trial, and the table of them (CSV and Markdown)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

METRIC = "best_error_ratio"  # the in-training Error sum over the best PID's; lower is better

COLUMNS = ("trial", "seed", "settings", "status", "best_error_ratio", "best_steps", "success_pct",
           "smoothness", "meets_bar", "steps", "wall_s")
PERTURBED_COLUMNS = ("perturbed_error_ratio", "perturbed_success_pct", "meets_perturbed")


def trial_rows(results) -> list[dict[str, Any]]:
    rows = []
    for r in results:
        m = r.metrics or {}
        if r.error is not None:
            status = "error"
        elif m.get("finished"):
            status = "done"
        else:
            status = "stopped early" if m else "not started"
        rows.append({"trial": m.get("trial_id", Path(r.path).name), "seed": r.config["seed"],
                     "settings": r.config.get("settings", {}), "status": status,
                     "best_error_ratio": m.get(METRIC), "best_steps": m.get("best_steps"),
                     "success_pct": m.get("success_pct"), "smoothness": m.get("smoothness"),
                     "meets_bar": m.get("meets_bar"), "selection_key": m.get("selection_key"),
                     "steps": m.get("steps"), "perturbed": m.get("perturbed"),
                     "wall_s": None if m.get("wall_s") is None else round(m["wall_s"], 1),
                     "best_checkpoint": m.get("best_checkpoint")})
    return sorted(rows, key=lambda row: (row["seed"], json.dumps(row["settings"], sort_keys=True)))


def _cell(key: str, value: Any) -> str:
    if value is None:
        return "n/a"
    if key == "settings":
        return " ".join(f"{k}={v}" for k, v in value.items()) or "(recipe)"
    if key.endswith("success_pct"):
        return "/".join(f"{v:.1f}" for v in value)
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3f}" if key.endswith("error_ratio") else f"{value:.1f}"
    return str(value)


def write_tables(rows: list[dict[str, Any]], out: Path, perturbed: bool = False) -> None:
    columns = COLUMNS + (PERTURBED_COLUMNS if perturbed else ())
    with (out / "results.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        writer.writerows([[_cell(k, row[k]) for k in columns] for row in rows])
    head = ("trial", "seed", "settings", "status", "best Error ratio vs PID", "at step",
            "Success % r/p/y", "smoothness µs/step", "meets the deployable bar", "steps", "wall s")
    if perturbed:
        head += ("perturbed Error ratio vs PID, worse task", "perturbed Success % r/p/y, lower task",
                 "meets the perturbed lines, rest and in flight")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(_cell(k, row[k]) for k in columns) + " |" for row in rows]
    (out / "results.md").write_text("\n".join(lines) + "\n")
