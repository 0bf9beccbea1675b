"""Markdown tables of `gomatch-sim eval` reports for the model card.

    python3 tools/train/eval_table.py DIR

reads every DIR/<scene>-<precision>.json written by tools/train/ship_model.sh (protocol seed 0) and
prints one row per scene and precision: queries, failures, reprojection AUC @1/5/10 px, rotation
error quartiles, mean inliers and matching time per query. When DIR also holds reports of further
seeds (<scene>-<precision>-seed<S>.json), a second table gives each AUC's mean over all seeds with
its range, and the f16 - f32 and int8 - f32 differences of the means with a 95 % paired bootstrap
interval over the queries (the same resampled queries for both precisions and every seed), which says
how far the difference could move with other queries of the same scene. With `--baseline OTHER_DIR`
(reports of another model, same protocol), it also prints each scene's and precision's difference to that
model over the seeds both hold, with the same interval: the test for shipping a new export. For seed-0
reports that record `correct`, a last table splits the queries into those localized within 10 px and the
others, with the medians of their ground-truth merged matches and inliers (matching vs pose failures).
When DIR holds oracle reports (<scene>-oracle.json, written by tools/train/eval_all.sh on the same queries),
a validation table gives per scene and precision the model's and the oracle's AUC, failures, and the true
matches among merged matches and inliers (medians over the queries), and per precision the mean over the
scenes with the mean ratio of model to oracle AUC @5 px. Standard library only.

    python3 tools/train/eval_table.py DIR [--baseline OTHER_DIR]
"""

import argparse
import json
import random
from statistics import median
from pathlib import Path

PRECISIONS = ["f32", "f16", "int8"]
LOCALIZED_PX = 10.0  # reprojection error under which the last table counts a query as localized
AUC_KEYS = ("auc_1px", "auc_5px", "auc_10px")
AUC_THRESHOLDS_PX = (1.0, 5.0, 10.0)
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0


def row(report: dict, precision: str) -> str:
    auc = " / ".join(f"{report[k]:.2f}" for k in AUC_KEYS)
    quartiles = report["rot_deg_q"]  # None when no query was localized
    rot = " / ".join(f"{v:.2f}" for v in quartiles) if quartiles else "-"
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


def error_auc(errors: list[float], threshold: float) -> float:
    """Area under the recall curve of the errors up to `threshold`, over the threshold, in percent: the
    trapezoidal rule of `error_auc` in host-sim/src/protocol/mod.rs (a failed query has an infinite error)."""
    area, last_error, last_recall = 0.0, 0.0, 0.0
    for i, error in enumerate(sorted(errors)):
        if error >= threshold:
            break
        recall = (i + 1) / len(errors)
        area += (error - last_error) * (recall + last_recall) * 0.5
        last_error, last_recall = error, recall
    area += (threshold - last_error) * last_recall
    return 100.0 * area / threshold


def query_errors(report: dict) -> dict[int, float]:
    """Reprojection error per query image id; infinite for a failed query."""
    return {
        q["image_id"]: q["reprojection_px"] if q["reprojection_px"] is not None else float("inf")
        for q in report["per_query"]
    }


def mean_aucs(errors_per_seed: list[dict[int, float]], queries: list[int]) -> list[float]:
    """Each threshold's AUC over the seeds' errors of the given query ids (repeats allowed), averaged."""
    return [
        sum(error_auc([errors[q] for q in queries], t) for errors in errors_per_seed) / len(errors_per_seed)
        for t in AUC_THRESHOLDS_PX
    ]


def errors_difference(base: list[dict[int, float]], other: list[dict[int, float]], queries: list[int]) -> list[float]:
    return [b - a for a, b in zip(mean_aucs(base, queries), mean_aucs(other, queries))]


def mean_auc_difference(base: list[dict], other: list[dict], queries: list[int]) -> list[float]:
    """Mean AUC over the seeds of `other` minus that of `base`, on the given query ids (repeats allowed)."""
    return errors_difference([query_errors(r) for r in base], [query_errors(r) for r in other], queries)


def bootstrap_interval(base: list[dict], other: list[dict]) -> list[tuple[float, float]]:
    """95 % percentile interval of `mean_auc_difference` when the queries are resampled with replacement
    (seeded, so the table is reproducible)."""
    base_errors, other_errors = [query_errors(r) for r in base], [query_errors(r) for r in other]
    queries = sorted(base_errors[0])
    rng = random.Random(BOOTSTRAP_SEED)
    samples = [
        errors_difference(base_errors, other_errors, rng.choices(queries, k=len(queries)))
        for _ in range(BOOTSTRAP_RESAMPLES)
    ]
    low, high = int(0.025 * BOOTSTRAP_RESAMPLES), int(0.975 * BOOTSTRAP_RESAMPLES) - 1
    return [(sorted(column)[low], sorted(column)[high]) for column in zip(*samples)]


def difference_line(base: list[dict], other: list[dict], label: str) -> str:
    diff = " / ".join(f"{b - a:+.2f}" for a, b in zip(auc_means(base), auc_means(other)))
    line = f"{base[0]['scene']}: {label}, mean AUC @1/5/10 px: {diff}"
    reports = base + other
    query_sets = {frozenset(query_errors(r)) for r in reports} if all("per_query" in r for r in reports) else set()
    if len(query_sets) == 1:
        spans = " / ".join(f"[{lo:+.2f}, {hi:+.2f}]" for lo, hi in bootstrap_interval(base, other))
        line += f" (95 % bootstrap interval over the queries: {spans})"
    return line


def seed_row(scene: str, precision: str, reports: list[dict]) -> str:
    means = auc_means(reports)
    ranges = [(min(r[k] for r in reports), max(r[k] for r in reports)) for k in AUC_KEYS]
    cells = " / ".join(f"{m:.2f}" for m in means)
    spans = " / ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in ranges)
    seeds = ", ".join(str(r["seed"]) for r in reports)
    return f"| {scene} | {precision} | {seeds} | {cells} | {spans} |"


def true_match_cells(queries: list[dict]) -> str:
    """Count, then medians of the true merged matches (range), merged matches, true inliers, inliers."""
    if not queries:
        return "0 | - | -"
    true_merged = [q["correct"]["merged"] for q in queries]
    merged = [q["counts"]["merged"] for q in queries]
    true_inliers = [q["correct"]["inliers"] for q in queries]
    inliers = [q["counts"]["inliers"] for q in queries]
    return (f"{len(queries)} | {median(true_merged):g} ({min(true_merged):g}-{max(true_merged):g}) of "
            f"{median(merged):g} | {median(true_inliers):g} of {median(inliers):g}")


def true_match_row(report: dict, precision: str) -> str | None:
    """Queries localized within `LOCALIZED_PX` against the others: how many of their merged matches
    and inliers are ground-truth pairs (medians), or None for reports without that record."""
    queries = report.get("per_query", [])
    if not queries or any(q.get("correct") is None for q in queries):
        return None
    within, others = [], []
    for q in queries:
        localized = q["reprojection_px"] is not None and q["reprojection_px"] < LOCALIZED_PX
        (within if localized else others).append(q)
    return f"| {report['scene']} | {precision} | {true_match_cells(within)} | {true_match_cells(others)} |"


def true_match_table(reports: dict) -> None:
    rows = [true_match_row(found[0], precision) for (_, precision), found in reports.items()]
    rows = [r for r in rows if r is not None]
    if rows:
        print()
        print(f"| scene | weights | queries within {LOCALIZED_PX:g} px "
              "| their true merged matches (range) of merged, median | true inliers of inliers | other queries "
              "| their true merged (range) of merged | true inliers of inliers |")
        print("|---|---|---|---|---|---|---|---|")
        print("\n".join(rows))


def baseline_lines(reports: dict, baseline: Path) -> list[str]:
    """Per scene and precision: this model minus the baseline's, over the seeds both hold."""
    lines = []
    for (scene, precision), found in reports.items():
        base = seed_reports(baseline, scene, precision)
        seeds = {r["seed"] for r in found} & {r["seed"] for r in base}
        if seeds:
            mine = [r for r in found if r["seed"] in seeds]
            theirs = [r for r in base if r["seed"] in seeds]
            lines.append(difference_line(theirs, mine, f"{precision} - baseline {precision}"))
    return lines


def aucs(report: dict) -> str:
    return " / ".join(f"{report[k]:.2f}" for k in AUC_KEYS)


def median_correct(report: dict, stage: str) -> str:
    """Median over the queries of the true matches among a stage's matches, and of the stage's matches."""
    queries = [q for q in report.get("per_query", []) if q.get("correct") is not None]
    if not queries:
        return "-"
    return f"{median(q['correct'][stage] for q in queries):g} of {median(q['counts'][stage] for q in queries):g}"


def validation_table(folder: Path, reports: dict) -> None:
    """Model against the oracle on the same queries, per scene and precision, and means over the scenes."""
    oracles = {path.name[: -len("-oracle.json")]: json.loads(path.read_text()) for path in sorted(folder.glob("*-oracle.json"))}
    rows = [(scene, p, found[0], oracles[scene]) for (scene, p), found in reports.items() if scene in oracles]
    if not rows:
        return
    print()
    print("| scene | weights | queries | failures (oracle) | AUC @1/5/10 px | oracle AUC @1/5/10 px "
          "| true merged of merged, median | true inliers of inliers, median |")
    print("|---|---|---|---|---|---|---|---|")
    for _, precision, report, oracle in rows:
        print(f"| {report['scene']} | {precision} | {report['queries']} | {report['failures']} ({oracle['failures']}) "
              f"| {aucs(report)} | {aucs(oracle)} | {median_correct(report, 'merged')} "
              f"| {median_correct(report, 'inliers')} |")
    print()
    print("| weights | scenes | mean AUC @1/5/10 px | mean oracle AUC @1/5/10 px | mean AUC @5 px / oracle AUC @5 px |")
    print("|---|---|---|---|---|")
    for precision in PRECISIONS:
        chosen = [(r, o) for _, p, r, o in rows if p == precision]
        if not chosen:
            continue
        mean = lambda values: sum(values) / len(values)  # noqa: E731
        model = " / ".join(f"{mean([r[k] for r, _ in chosen]):.2f}" for k in AUC_KEYS)
        oracle = " / ".join(f"{mean([o[k] for _, o in chosen]):.2f}" for k in AUC_KEYS)
        ratio = mean([r["auc_5px"] / o["auc_5px"] if o["auc_5px"] > 0 else 0.0 for r, o in chosen])
        print(f"| {precision} | {len(chosen)} | {model} | {oracle} | {ratio:.3f} |")


def main(folder: Path, baseline: Path | None = None) -> None:
    scenes = sorted({path.name[: -len(f"-{p}.json")] for p in PRECISIONS for path in folder.glob(f"*-{p}.json")})
    reports = {(scene, p): seed_reports(folder, scene, p) for scene in scenes for p in PRECISIONS}
    reports = {key: found for key, found in reports.items() if found}
    print("| scene | weights | queries | failures | AUC @1/5/10 px | rotation q25/50/75 (deg) "
          "| mean inliers | ms per query |")
    print("|---|---|---|---|---|---|---|---|")
    for (_, precision), found in reports.items():
        print(row(found[0], precision))
    if any(len(found) > 1 for found in reports.values()):
        seed_tables(scenes, reports)
    true_match_table(reports)
    validation_table(folder, reports)
    if baseline is not None:
        print()
        print("\n".join(baseline_lines(reports, baseline)))


def seed_tables(scenes: list[str], reports: dict) -> None:
    print()
    print("| scene | weights | seeds | mean AUC @1/5/10 px | range over the seeds |")
    print("|---|---|---|---|---|")
    for (_, precision), found in reports.items():
        print(seed_row(found[0]["scene"], precision, found))
    print()
    for scene in scenes:
        for precision in ("f16", "int8"):
            f32, other = reports.get((scene, "f32")), reports.get((scene, precision))
            if f32 and other:
                print(difference_line(f32, other, f"{precision} - f32"))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path)
    parser.add_argument("--baseline", type=Path, help="reports of another model to compare with")
    args = parser.parse_args()
    main(args.folder, args.baseline)
