"""Training samples: reading the `gomatch-dataset` safetensors format and per-epoch point subsampling.

File format: tools/train/README.md, "Dataset file format" (written by `gomatch-sim dataset`). One sample = one query image and
one co-visible database view: pts2d (N2, 2) and pts3d (N3, 2) bearing coordinates and match (N2,) = index of the
GT 3D point of each keypoint or -1.

Subsampling (paper supp. "Outlier Rate Control", "Keypoint Number Control"): inliers (GT pairs) are kept or dropped
jointly, the outliers of each set are subsampled to bound the outlier rate, everything is scaled down to a point
budget, and both sets are randomly permuted.
"""

import json
from dataclasses import dataclass

import numpy as np
from safetensors import safe_open

FORMAT_NAME = "gomatch-dataset"
FORMAT_VERSION = "1"


@dataclass
class Sample:
    pts2d: np.ndarray  # (N2, 2) float32
    pts3d: np.ndarray  # (N3, 2) float32
    match: np.ndarray  # (N2,) int64, index into pts3d or -1
    name: str  # "<scene>/q<query>/v<view>" for messages


def load_samples(path: str) -> list:
    """All samples of one dataset file, validated against the format."""
    with safe_open(path, "np") as f:
        metadata = f.metadata() or {}
        if metadata.get("format") != FORMAT_NAME or metadata.get("version") != FORMAT_VERSION:
            raise ValueError(
                f"{path}: not a {FORMAT_NAME} v{FORMAT_VERSION} file "
                f"(format={metadata.get('format')!r}, version={metadata.get('version')!r})"
            )
        t = {name: f.get_tensor(name) for name in f.keys()}
    scenes = json.loads(metadata.get("scenes", "[]"))
    off2d, off3d = t["offsets2d"], t["offsets3d"]
    count = len(off2d) - 1
    if len(off3d) != count + 1 or off2d[-1] != len(t["pts2d"]) or off3d[-1] != len(t["pts3d"]):
        raise ValueError(f"{path}: offsets do not cover pts2d ({len(t['pts2d'])}) / pts3d ({len(t['pts3d'])})")
    if np.any(np.diff(off2d) < 0) or np.any(np.diff(off3d) < 0) or off2d[0] != 0 or off3d[0] != 0:
        raise ValueError(f"{path}: offsets are not non-decreasing from 0")
    samples = []
    for s in range(count):
        pts2d = t["pts2d"][off2d[s] : off2d[s + 1]].astype(np.float32)
        pts3d = t["pts3d"][off3d[s] : off3d[s + 1]].astype(np.float32)
        match = t["match"][off2d[s] : off2d[s + 1]].astype(np.int64)
        if np.any(match < -1) or np.any(match >= len(pts3d)):
            raise ValueError(f"{path}: sample {s} has match indices outside [-1, {len(pts3d)})")
        matched = match[match >= 0]
        if len(np.unique(matched)) != len(matched):
            raise ValueError(f"{path}: sample {s} matches one 3D point to several keypoints")
        if not (np.isfinite(pts2d).all() and np.isfinite(pts3d).all()):
            raise ValueError(f"{path}: sample {s} has non-finite coordinates")
        scene_id = int(t["scene"][s])
        scene = scenes[scene_id] if 0 <= scene_id < len(scenes) else str(scene_id)
        samples.append(Sample(pts2d, pts3d, match, f"{scene}/q{int(t['query'][s])}/v{int(t['view'][s])}"))
    return samples


def point_counts(inliers: int, outliers2d: int, outliers3d: int, outlier_rate, max_points: int, min_points: int):
    """Numbers (inliers, 2D outliers, 3D outliers) to keep, or None when the sample is too small.

    outlier_rate = (low, high): when either set's outlier rate is below `low`, inliers are cut to reach it; each
    set's outliers are capped so its rate is at most `high`. Then all counts are scaled down so the larger set has
    at most `max_points` points (<= 0: no budget). A result whose smaller set has fewer than `min_points` is None.
    """
    low, high = outlier_rate
    if low > 0 and min(outliers2d / max(inliers + outliers2d, 1), outliers3d / max(inliers + outliers3d, 1)) < low:
        inliers = int(min(outliers2d, outliers3d) * (1 - low) / low)
    max_outliers = int(inliers * high / (1 - high)) if 0 <= high < 1 else max(outliers2d, outliers3d)
    outliers2d = min(outliers2d, max_outliers)
    outliers3d = min(outliers3d, max_outliers)
    largest = inliers + max(outliers2d, outliers3d)
    if max_points > 0 and largest > max_points:
        scale = max_points / largest
        inliers, outliers2d, outliers3d = int(scale * inliers), int(scale * outliers2d), int(scale * outliers3d)
    if inliers + min(outliers2d, outliers3d) < min_points:
        return None
    return inliers, outliers2d, outliers3d


def subsample(sample: Sample, rng: np.random.Generator, outlier_rate, max_points: int, min_points: int):
    """(pts2d, pts3d, match) drawn from `sample` with `point_counts`, both sets randomly permuted; or None."""
    matched2d = np.flatnonzero(sample.match >= 0)
    matched3d = sample.match[matched2d]
    outliers2d = np.flatnonzero(sample.match < 0)
    is_matched3d = np.zeros(len(sample.pts3d), dtype=bool)
    is_matched3d[matched3d] = True
    outliers3d = np.flatnonzero(~is_matched3d)
    counts = point_counts(len(matched2d), len(outliers2d), len(outliers3d), outlier_rate, max_points, min_points)
    if counts is None:
        return None
    n_in, n_out2d, n_out3d = counts

    keep_in = rng.choice(len(matched2d), n_in, replace=False)
    ids2d = np.concatenate([matched2d[keep_in], rng.choice(outliers2d, n_out2d, replace=False)])
    ids3d = np.concatenate([matched3d[keep_in], rng.choice(outliers3d, n_out3d, replace=False)])
    # Before permuting, 2D keypoint i < n_in matches 3D point i.
    match = np.concatenate([np.arange(n_in), np.full(n_out2d, -1)])
    order3d = rng.permutation(len(ids3d))
    new_index3d = np.argsort(order3d)
    match[:n_in] = new_index3d[match[:n_in]]
    order2d = rng.permutation(len(ids2d))
    return sample.pts2d[ids2d[order2d]], sample.pts3d[ids3d[order3d]], match[order2d]
