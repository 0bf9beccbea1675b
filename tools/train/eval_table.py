"""Markdown tables of `gomatch-sim eval` reports for the model card.

    python3 tools/train/eval_table.py DIR

reads every DIR/<scene>-<precision>.json written by tools/train/ship_model.sh (protocol seed 0) and
prints one row per scene and precision: queries, failures, reprojection AUC @1/5/10 px, rotation
error quartiles, mean inliers and matching time per query. When DIR also holds reports of further
seeds (<scene>-<precision>-seed<S>.json), a second table gives each AUC's mean over all seeds with
its range, and the int8 - f32 difference of the means. Standard library only.
"""

import json
import sys
from pathlib import Path

PRECISIONS = ["f32", "f16", "int8"]
AUC_KEYS = ("auc_1px", "auc_5px", "auc_10px")


def row(report: dict, precision: str) -> str:
    auc = " / ".join(f"{report[k]:.2f}" for k in AUC_KEYS)
    rot = " / ".join(f"{v:.2f}" for v in report["rot_deg_q"])
    inliers = report["mean_counts"]["inliers"]
    ms = report["mean_timings_ms"]["total"]
    return (
        f"| {report['scene']} | {precision} | {report['queries']} | {report['failures']} | {auc} "
        f"| {rot} | {inliers:.1f} | {ms:.0f} |"
    )


def seed_reports(folder: Path, scene: str, precision: str) -> list[dict]:
    """The seed-0 report followed by those of the further seeds, in seed order."""
    paths = [folder / f"{scene}-{precision}.json"]
    paths += sorted(folder.glob(f"{scene}-{precision}-seed*.json"), key=lambda p: int(p.stem.rsplit("seed", 1)[1]))
    return [json.loads(p.read_text()) for p in paths if p.exists()]


def auc_means(reports: list[dict]) -> list[float]:
    """Mean of each AUC threshold over the reports."""
    return [sum(r[k] for r in reports) / len(reports) for k in AUC_KEYS]


def seed_row(scene: str, precision: str, reports: list[dict]) -> str:
    means = auc_means(reports)
    ranges = [(min(r[k] for r in reports), max(r[k] for r in reports)) for k in AUC_KEYS]
    cells = " / ".join(f"{m:.2f}" for m in means)
    spans = " / ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in ranges)
    seeds = ", ".join(str(r["seed"]) for r in reports)
    return f"| {scene} | {precision} | {seeds} | {cells} | {spans} |"


def main(folder: Path) -> None:
    scenes = [path.name[: -len("-f32.json")] for path in sorted(folder.glob("*-f32.json"))]
    reports = {(scene, p): seed_reports(folder, scene, p) for scene in scenes for p in PRECISIONS}
    reports = {key: found for key, found in reports.items() if found}
    print("| scene | weights | queries | failures | AUC @1/5/10 px | rotation q25/50/75 (deg) "
          "| mean inliers | ms per query |")
    print("|---|---|---|---|---|---|---|---|")
    for (_, precision), found in reports.items():
        print(row(found[0], precision))
    if all(len(found) == 1 for found in reports.values()):
        return
    print()
    print("| scene | weights | seeds | mean AUC @1/5/10 px | range over the seeds |")
    print("|---|---|---|---|---|")
    for (_, precision), found in reports.items():
        print(seed_row(found[0]["scene"], precision, found))
    print()
    for scene in scenes:
        f32, int8 = reports.get((scene, "f32")), reports.get((scene, "int8"))
        if f32 and int8:
            diff = " / ".join(f"{b - a:+.2f}" for a, b in zip(auc_means(f32), auc_means(int8)))
            print(f"{f32[0]['scene']}: int8 - f32, mean AUC @1/5/10 px: {diff}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
