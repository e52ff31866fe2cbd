"""What the generated tables' modules share (`benchmarks.tables` and its table modules import it, never the other
way): a results file read with the missing-file message, one error model's per-object table in
benchmarks.generalise's format, a plain mean, and counts grouped by thousands."""

from __future__ import annotations

import json
from pathlib import Path


def read(results: Path, name: str) -> dict:
    path = results / name
    if not path.exists():
        raise SystemExit(f"benchmarks.tables: {path} is missing; the table needs it")
    return json.loads(path.read_text())


def object_table(report: dict, model: str) -> list[str]:
    """One error model's per-object table in benchmarks.generalise's format, without its heading."""
    from benchmarks.generalise_tables import model_table  # the matspray imports only when a table is made

    result = report["models"][model]
    return model_table(model, result["objects"], result["summary"], report["settings"]["variants"])[2:]


def mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)


def grouped(count: int) -> str:
    """12345 -> "12 345": the docs' way of writing counts."""
    return f"{count:,}".replace(",", " ")
