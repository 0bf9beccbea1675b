"""Markdown table of `gomatch-sim eval` reports for the model card.

    python3 tools/train/eval_table.py DIR

reads every DIR/<scene>-<precision>.json written by tools/train/ship_model.sh and prints one row
per scene and precision: queries, failures, reprojection AUC @1/5/10 px, rotation error quartiles,
mean inliers and matching time per query. Standard library only.
"""

import json
import sys
from pathlib import Path

PRECISIONS = ["f32", "f16", "int8"]


def row(report: dict, precision: str) -> str:
    auc = " / ".join(f"{report[k]:.2f}" for k in ("auc_1px", "auc_5px", "auc_10px"))
    rot = " / ".join(f"{v:.2f}" for v in report["rot_deg_q"])
    inliers = report["mean_counts"]["inliers"]
    ms = report["mean_timings_ms"]["total"]
    return (
        f"| {report['scene']} | {precision} | {report['queries']} | {report['failures']} | {auc} "
        f"| {rot} | {inliers:.1f} | {ms:.0f} |"
    )


def main(folder: Path) -> None:
    print("| scene | weights | queries | failures | AUC @1/5/10 px | rotation q25/50/75 (deg) "
          "| mean inliers | ms per query |")
    print("|---|---|---|---|---|---|---|---|")
    for path in sorted(folder.glob("*-f32.json")):
        scene = path.name[: -len("-f32.json")]
        for precision in PRECISIONS:
            report_path = folder / f"{scene}-{precision}.json"
            if report_path.exists():
                print(row(json.loads(report_path.read_text()), precision))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
