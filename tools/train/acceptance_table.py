#!/usr/bin/env python3
"""Acceptance figures of `gomatch-sim eval` reports: per report the poses with >= 4 inliers (right / wrong),
how many the rule the reports were written with accepted and how many of those were wrong, and the totals.

    python3 tools/train/acceptance_table.py REPORT.json [...]
"""
import json
import sys
from pathlib import Path


def main(paths: list[str]) -> None:
    print("| scene | candidates (right / wrong) | accepted | accepted wrong | recall |")
    print("|---|---|---|---|---|")
    total = {"candidates": 0, "candidates_right": 0, "accepted": 0, "accepted_wrong": 0}
    for path in paths:
        report = json.loads(Path(path).read_text())
        a = report["acceptance"]
        for key in total:
            total[key] += a[key]
        print(line(report["scene"], a))
    print(line(f"all {len(paths)}", total))


def line(name: str, a: dict) -> str:
    right, cands = a["candidates_right"], a["candidates"]
    kept = a["accepted"] - a["accepted_wrong"]
    recall = f"{100 * kept / right:.1f} % ({kept} of {right})" if right else "-"
    return f"| {name} | {cands} ({right} / {cands - right}) | {a['accepted']} | {a['accepted_wrong']} | {recall} |"


if __name__ == "__main__":
    main(sys.argv[1:])
