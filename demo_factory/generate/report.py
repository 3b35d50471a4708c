"""The generation report: every job's figures in a folder, as ``report.json``, a table and a chart.

``demo-factory generate`` writes one ``generation_summary_<task>_<split>.json`` per job; the report
gathers those found under a folder (a task's train and test jobs, or a whole suite).
"""

from __future__ import annotations

import json
from pathlib import Path

from demo_factory.generate.folder import SUMMARY_GLOB
COLUMNS = ("task", "split", "requested", "kept", "failed", "success", "attempts 1/2/3+", "plan median s",
           "plan p95 s", "s/episode", "total s")


def collect_summaries(folder: str | Path) -> list[dict]:
    """Every job summary under ``folder``, sorted by task and split."""
    summaries = []
    for path in sorted(Path(folder).rglob(SUMMARY_GLOB)):
        try:
            summaries.append(json.loads(path.read_text()))
        except (OSError, ValueError):
            continue  # a damaged summary only costs the report one row
    return sorted(summaries, key=lambda s: (s["task"], s["split"]))


def report_rows(summaries: list[dict]) -> list[dict]:
    """One row per job with the report's figures."""
    rows = []
    for s in summaries:
        histogram = {int(k): v for k, v in s.get("planner_attempts_histogram", {}).items()}
        rows.append({
            "task": s["task"],
            "split": s["split"],
            "requested": s["requested"],
            "kept": s["kept"],
            "failed": len(s["failed"]),
            "failure_reasons": s.get("failure_reasons", {}),
            "expert_success_rate": s["kept"] / s["requested"] if s["requested"] else 0.0,
            "planner_attempts_histogram": {str(k): histogram[k] for k in sorted(histogram)},
            "planning_seconds_median": s.get("planning_seconds_median"),
            "planning_seconds_p95": s.get("planning_seconds_p95"),
            "seconds_per_episode": s.get("seconds_per_episode"),
            "total_seconds": s.get("total_seconds"),
            "command": s.get("command"),
        })
    return rows


def _cell(value, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def report_table(rows: list[dict]) -> str:
    """A Markdown table of the rows (readable as plain text too)."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        h = {int(k): v for k, v in r["planner_attempts_histogram"].items()}
        attempts = f"{h.get(1, 0)}/{h.get(2, 0)}/{sum(v for k, v in h.items() if k >= 3)}"
        cells = [r["task"], r["split"], r["requested"], r["kept"], r["failed"],
                 f"{100 * r['expert_success_rate']:.1f}%", attempts, _cell(r["planning_seconds_median"], 3),
                 _cell(r["planning_seconds_p95"], 3), _cell(r["seconds_per_episode"]), _cell(r["total_seconds"], 1)]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def write_report(folder: str | Path) -> Path | None:
    """Write ``report.json``, ``report.md`` and ``report.png`` into ``folder``; None if no job ran there."""
    folder = Path(folder)
    rows = report_rows(collect_summaries(folder))
    if not rows:
        return None
    (folder / "report.json").write_text(json.dumps({"jobs": rows}, indent=2) + "\n")
    reasons = sorted({reason for r in rows for reason in r["failure_reasons"]})
    notes = "".join(f"- {r['task']}/{r['split']}: " + ", ".join(f"{k}: {v}" for k, v in r["failure_reasons"].items()) + "\n"
                    for r in rows if r["failure_reasons"])
    (folder / "report.md").write_text(
        "# Generation report\n\n" + report_table(rows)
        + (f"\nFailed episodes by reason ({', '.join(reasons)}):\n{notes}" if notes else "\nNo failed episodes.\n")
        + "\nAttempts: planned transitions that needed 1, 2, or 3+ seeded OMPL attempts (at most 10).\n"
    )
    _chart(folder / "report.png", rows)
    return folder / "report.json"


def _chart(path: Path, rows: list[dict]) -> None:
    """Planner attempts per job (stacked by attempt count) beside seconds per episode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['task']}\n{r['split']}" for r in rows]
    figure, (attempts_axis, time_axis) = plt.subplots(1, 2, figsize=(max(6.0, 1.4 * len(rows) + 3), 3.4), dpi=100)
    bottom = [0] * len(rows)
    for attempt in range(1, 11):
        counts = [r["planner_attempts_histogram"].get(str(attempt), 0) for r in rows]
        if any(counts):
            attempts_axis.bar(labels, counts, bottom=bottom, label=f"{attempt} attempt{'s' if attempt > 1 else ''}")
            bottom = [b + c for b, c in zip(bottom, counts)]
    attempts_axis.set_title("planned transitions by attempts used", fontsize=9)
    if any(bottom):  # a job of only straight moves planned nothing: no bars, no legend
        attempts_axis.legend(fontsize=7)
    time_axis.bar(labels, [r["seconds_per_episode"] or 0.0 for r in rows], color="#55A868")
    time_axis.set_title("seconds per episode", fontsize=9)
    for axis in (attempts_axis, time_axis):
        axis.tick_params(axis="x", labelsize=7)
    figure.tight_layout()
    figure.savefig(path, metadata={"Software": None})
    plt.close(figure)
