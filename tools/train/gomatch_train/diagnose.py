"""Where the matcher fails: the trainer's match precision and recall by viewpoint change and by outlier rate.

    python -m gomatch_train.diagnose MODEL.safetensors DATA.safetensors [--max-points 1024] [--rates 0.5 0.7 0.85]
        [--scene colmap/mouse] [--limit N] [--seed 0] [--threads 2] [--rotate DEG]

Two markdown tables of pooled match precision / recall (the mutual assignment's matches, as `validate` counts them):
- by viewpoint change, at every sample's own outlier rate: the median angle between a GT match's query bearing and
  its 3D point's bearing in the view's frame (relative rotation and parallax together);
- per scene (synthetic scenes pooled by kind), with the median viewpoint change and the mean share of keypoints
  with a match (before the caps of `--max-points`), at the samples' own outlier rate and at each controlled
  keypoint outlier rate of `--rates` (the trainer's `--outlier-rate R R`: outliers or inliers dropped to reach R).
`--rotate DEG` first turns every view's bearings by DEG degrees about a random axis (points then behind the camera
are dropped): what a rotation alone, without parallax, costs. `--scene` keeps one scene's samples, `--limit N` N
samples drawn at random.
"""

import argparse
from dataclasses import replace

import numpy as np
import torch

from .dataset import Sample, load_samples
from .evaluate import Totals, assess
from .export import load_export
from .runtime import configure_cpu
from .synthetic import rotation
from .train import NO_OUTLIER_CONTROL, to_tensors, validation_draw

ANGLE_BINS = (0, 2, 5, 10, 20, 40, 180)
MIN_DEPTH = 0.2  # a rotated bearing with z below this is behind (or grazing) the turned camera


def viewpoint_change(sample: Sample) -> float:
    """Median angle in degrees between the two bearings of the sample's GT matches; NaN without a match."""
    matched = sample.match >= 0
    if not matched.any():
        return float("nan")
    query = unit_bearings(sample.pts2d[matched])
    view = unit_bearings(sample.pts3d[sample.match[matched]])
    return float(np.degrees(np.median(np.arccos(np.clip((query * view).sum(1), -1.0, 1.0)))))


def unit_bearings(plane: np.ndarray) -> np.ndarray:
    rays = np.column_stack([plane, np.ones(len(plane))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def rotated_view(sample: Sample, degrees: float, rng: np.random.Generator) -> Sample:
    """The sample with its view's camera turned by `degrees` about a random axis through its centre."""
    axis = rng.normal(size=3)
    turn = rotation(axis / np.linalg.norm(axis) * np.radians(degrees))
    rays = np.column_stack([sample.pts3d, np.ones(len(sample.pts3d))]) @ turn.T
    kept = rays[:, 2] > MIN_DEPTH
    new_index = np.full(len(rays), -1)
    new_index[kept] = np.arange(kept.sum())
    match = np.where(sample.match >= 0, new_index[np.maximum(sample.match, 0)], -1)
    pts3d = (rays[kept, :2] / rays[kept, 2:]).astype(np.float32)
    return replace(sample, pts3d=pts3d, match=match)


def scene_group(name: str) -> str:
    """"colmap/mouse" for "colmap/mouse/q3/v7"; synthetic scenes pooled by kind ("collection", "synthetic")."""
    parts = name.split("/")
    return parts[0] if parts[0] in ("synthetic", "collection") else "/".join(parts[:-2])


@torch.no_grad()
def totals_by(model, samples: list, keys: list, seed: int, max_points: int, rate) -> dict:
    """Totals per key (and "all") over the samples, each drawn as `train.validation_set` draws it."""
    groups = {}
    for index, (sample, key) in enumerate(zip(samples, keys)):
        drawn = validation_draw(sample, index, seed, max_points, rate)
        if drawn is None:
            continue
        pts2d, pts3d, match = to_tensors(drawn, "cpu")
        outcome = assess(model(pts2d, pts3d), match, model.config.match_threshold)
        for group in (key, "all"):
            groups.setdefault(group, Totals()).add(outcome)
    return groups


def cell(totals: Totals | None) -> str:
    if totals is None:
        return ""
    s = totals.summary()
    return f"{s['match_precision']:.3f} / {s['match_recall']:.3f}"


def angle_table(model, samples: list, seed: int, max_points: int) -> str:
    angles = [viewpoint_change(s) for s in samples]
    bins = [next((f"{lo}-{hi}" for lo, hi in zip(ANGLE_BINS, ANGLE_BINS[1:]) if lo <= a < hi), "none") for a in angles]
    groups = totals_by(model, samples, bins, seed, max_points, tuple(NO_OUTLIER_CONTROL))
    rows = ["| viewpoint change (deg) | samples | GT matches per sample | match P / R |", "|---|---|---|---|"]
    for label in [f"{lo}-{hi}" for lo, hi in zip(ANGLE_BINS, ANGLE_BINS[1:])] + ["none", "all"]:
        if label in groups:
            t = groups[label]
            rows.append(f"| {label} | {t.samples} | {t.counts['gt_matches'] / t.samples:.1f} | {cell(t)} |")
    return "\n".join(rows)


def rate_table(model, samples: list, seed: int, max_points: int, rates: list) -> str:
    keys = [scene_group(s.name) for s in samples]
    columns = [("own", tuple(NO_OUTLIER_CONTROL))] + [(f"{r:g}", (r, r)) for r in rates]
    results = [totals_by(model, samples, keys, seed, max_points, rate) for _, rate in columns]
    header = " | ".join(f"match P / R, outlier rate {label}" for label, _ in columns)
    rows = [
        f"| scene | samples | median viewpoint change (deg) | keypoints with a match | {header} |",
        "|---" * (4 + len(columns)) + "|",
    ]
    for key in sorted(set(keys)) + ["all"]:
        if key in results[0]:
            mine = [s for s, k in zip(samples, keys) if key in (k, "all")]
            change = np.nanmedian([viewpoint_change(s) for s in mine])
            matched = np.mean([(s.match >= 0).mean() for s in mine])
            cells = " | ".join(cell(r.get(key)) for r in results)
            rows.append(f"| {key} | {results[0][key].samples} | {change:.1f} | {matched:.3f} | {cells} |")
    return "\n".join(rows)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model")
    p.add_argument("data")
    p.add_argument("--max-points", type=int, default=1024)
    p.add_argument("--rates", type=float, nargs="*", default=[0.5, 0.7, 0.85], help="controlled outlier rates")
    p.add_argument("--scene", default=None, help="only the samples of this scene (e.g. colmap/sceaux)")
    p.add_argument("--limit", type=int, default=None, help="at most this many samples, drawn at random")
    p.add_argument("--rotate", type=float, default=0.0, help="turn each view's camera by this many degrees first")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    configure_cpu(args.threads)
    model = load_export(args.model).eval()
    samples = [s for s in load_samples(args.data) if args.scene is None or s.name.startswith(args.scene + "/")]
    rng = np.random.default_rng(args.seed)
    if args.limit is not None and args.limit < len(samples):
        samples = [samples[i] for i in np.sort(rng.choice(len(samples), args.limit, replace=False))]
    if args.rotate:
        samples = [rotated_view(s, args.rotate, rng) for s in samples]
    print(angle_table(model, samples, args.seed, args.max_points), end="\n\n")
    print(rate_table(model, samples, args.seed, args.max_points, args.rates))


if __name__ == "__main__":
    main()
