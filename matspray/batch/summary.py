"""DIR/summary.json and DIR/summary.md: one row per object and the paper-style averages over objects."""

from __future__ import annotations

from pathlib import Path

from matspray.eval.tables import average_tables, format_metric, markdown_table, tables_markdown
from matspray.rundir import write_json, write_text_atomic

MATERIAL_ROWS = ("relighting", "basecolor", "roughness", "metallic")
STATUS_WORDS = {"finished": "finished", "skipped": "finished before", "failed": "FAILED"}


def object_row(result: dict) -> dict:
    """The summary row of one object: status, error, seconds, seconds per stage and the full
    method's relighting and material metrics (None without ground truth or when it failed)."""
    ours = ((result.get("metrics") or {}).get("table1") or {}).get("Ours")
    return {
        "name": result["name"],
        "data": result["data"],
        "run": result["run"],
        "status": result["status"],
        "error": result["error"],
        "seconds": None if result["seconds"] is None else round(result["seconds"], 3),
        "span": result.get("span"),
        "stage_seconds": result["timings"],
        "metrics": None if ours is None else {row: ours[row] for row in MATERIAL_ROWS if row in ours},
    }


def batch_summary(results: list[dict], settings: dict, engine: str, wall_seconds: float) -> dict:
    """The content of summary.json: rows, failures, and the averages over the objects with metrics."""
    evaluated = [r["metrics"] for r in results if r["status"] != "failed" and r.get("metrics")]
    averages = average_tables(evaluated) if evaluated else None
    failed = [{"name": r["name"], "error": r["error"]} for r in results if r["status"] == "failed"]
    return {
        "title": f"MatSpray batch: {len(results)} objects, preset {settings['pipeline']['preset']}",
        "settings": settings,
        "engine": engine,
        "wall_seconds": round(wall_seconds, 3),
        "objects": [object_row(r) for r in results],
        "failed": failed,
        "averaged_over": len(evaluated),
        "averages": averages,
    }


def _cell(metrics: dict | None, row: str, metric: str) -> str:
    return format_metric((metrics or {}).get(row), metric)


def summary_markdown(summary: dict) -> str:
    """summary.md: the per-object table, seconds per stage, failures, then the averaged paper tables."""
    rows = summary["objects"]
    parts = [
        f"# {summary['title']}",
        f"- engine: {summary['engine']}; wall time {summary['wall_seconds']:.1f} s\n"
        f"- {len(rows) - len(summary['failed'])} of {len(rows)} objects finished; averages over the "
        f"{summary['averaged_over']} with ground truth",
    ]
    header = [
        "Object",
        "Status",
        "Relighting PSNR ↑",
        "SSIM ↑",
        "LPIPS ↓",
        "BaseColor PSNR ↑",
        "Roughness PSNR ↑",
        "Metallic PSNR ↑",
        "Seconds",
    ]
    table = [
        [
            r["name"],
            STATUS_WORDS[r["status"]],
            _cell(r["metrics"], "relighting", "psnr"),
            _cell(r["metrics"], "relighting", "ssim"),
            _cell(r["metrics"], "relighting", "lpips"),
            _cell(r["metrics"], "basecolor", "psnr"),
            _cell(r["metrics"], "roughness", "psnr"),
            _cell(r["metrics"], "metallic", "psnr"),
            "—" if r["seconds"] is None else f"{r['seconds']:.1f}",
        ]
        for r in rows
    ]
    parts.append("## Objects\n\n" + markdown_table(header, table))
    stages = list(dict.fromkeys(s for r in rows for s in r["stage_seconds"]))
    if stages:
        stage_rows = [[r["name"]] + [_seconds(r["stage_seconds"].get(s)) for s in stages] for r in rows]
        parts.append("## Seconds per stage\n\n" + markdown_table(["Object"] + stages, stage_rows))
    if summary["failed"]:
        parts.append("## Failures\n\n" + "\n".join(f"- **{f['name']}**: {f['error']}" for f in summary["failed"]))
    if summary["averages"]:
        averaged = tables_markdown(
            {**summary["averages"], "title": f"Averages over {summary['averaged_over']} objects"}
        )
        parts.append(averaged.replace("\n## ", "\n### ").replace("# ", "## ", 1).rstrip("\n"))
    return "\n\n".join(parts) + "\n"


def _seconds(value) -> str:
    return "—" if value is None else f"{float(value):.1f}"


def write_summary(out, summary: dict) -> tuple[Path, Path]:
    out = Path(out)
    write_json(out / "summary.json", summary)
    write_text_atomic(out / "summary.md", summary_markdown(summary))
    return out / "summary.json", out / "summary.md"
