"""Development aid: random two-view scenes written in the `gomatch-dataset` format.

Only for tests and benchmarks of the trainer; real training data comes from `gomatch-sim dataset`.
A database camera sits at the origin looking down +z at random 3D points; a query camera is a small random
motion away. pts3d are the points' bearings in the database view, pts2d the visible points' projections into the
query (with noise) plus random outlier keypoints, and match the mutual nearest neighbours closer than 1e-3 as in
the dataset's ground-truth protocol.

    python -m gomatch_train.synthetic OUT.safetensors --samples 50 --seed 0
"""

import argparse
import json

import numpy as np
import torch
from safetensors.torch import save_file

from .dataset import FORMAT_NAME, FORMAT_VERSION

GT_THRESHOLD = 1e-3
HALF_FOV = 0.6  # bearing-coordinate half extent of both cameras' images


def rotation(axis_angle: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(axis_angle)
    if angle == 0:
        return np.eye(3)
    k = axis_angle / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def mutual_matches(keypoints: np.ndarray, projections: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """For each keypoint the index of its mutual-nearest valid projection within GT_THRESHOLD, else -1."""
    match = np.full(len(keypoints), -1, dtype=np.int64)
    candidates = np.flatnonzero(valid)
    if len(candidates) == 0 or len(keypoints) == 0:
        return match
    d = np.linalg.norm(keypoints[:, None, :] - projections[None, candidates, :], axis=2)
    nearest3d = d.argmin(axis=1)
    nearest2d = d.argmin(axis=0)
    for i, j in enumerate(nearest3d):
        if nearest2d[j] == i and d[i, j] < GT_THRESHOLD:
            match[i] = candidates[j]
    return match


def random_sample(rng: np.random.Generator, n3d: int, n_detected: int, n_outliers2d: int, noise: float = 2e-4):
    """One (pts2d, pts3d, match) pair of views."""
    depth = rng.uniform(2.0, 8.0, n3d)
    xy = rng.uniform(-HALF_FOV, HALF_FOV, (n3d, 2)) * depth[:, None]
    world = np.column_stack([xy, depth])  # database camera frame = world frame
    pts3d = world[:, :2] / world[:, 2:]

    r = rotation(rng.normal(0.0, 0.08, 3))
    t = rng.normal(0.0, 0.3, 3)
    cam = world @ r.T + t
    in_front = cam[:, 2] > 0.1
    proj = cam[:, :2] / np.where(in_front, cam[:, 2], 1.0)[:, None]
    visible = in_front & (np.abs(proj) < HALF_FOV).all(axis=1)

    detected = rng.permutation(np.flatnonzero(visible))[:n_detected]
    inlier_kps = proj[detected] + rng.normal(0.0, noise, (len(detected), 2))
    outlier_kps = rng.uniform(-HALF_FOV, HALF_FOV, (n_outliers2d, 2))
    pts2d = rng.permutation(np.concatenate([inlier_kps, outlier_kps]))
    match = mutual_matches(pts2d, proj, visible)
    return pts2d.astype(np.float32), pts3d.astype(np.float32), match


def write_dataset(path: str, samples, scene: str = "synthetic/0000", protocol=None) -> None:
    """Write (pts2d, pts3d, match) triples as one dataset-format file."""
    off2d = np.cumsum([0] + [len(s[0]) for s in samples])
    off3d = np.cumsum([0] + [len(s[1]) for s in samples])
    tensors = {
        "pts2d": torch.from_numpy(np.concatenate([s[0] for s in samples]).astype(np.float32)),
        "pts3d": torch.from_numpy(np.concatenate([s[1] for s in samples]).astype(np.float32)),
        "match": torch.from_numpy(np.concatenate([s[2] for s in samples]).astype(np.int64)),
        "offsets2d": torch.from_numpy(off2d.astype(np.int64)),
        "offsets3d": torch.from_numpy(off3d.astype(np.int64)),
        "scene": torch.zeros(len(samples), dtype=torch.int64),
        "query": torch.arange(len(samples), dtype=torch.int64),
        "view": torch.arange(len(samples), dtype=torch.int64) + 1000,
    }
    metadata = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "scenes": json.dumps([scene]),
        "protocol": json.dumps(protocol or {"generator": "gomatch_train.synthetic"}),
    }
    save_file(tensors, path, metadata=metadata)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out")
    parser.add_argument("--samples", type=int, default=50)
    parser.add_argument("--points3d", type=int, default=600, help="3D points per database view")
    parser.add_argument("--detected", type=int, default=400, help="visible points detected as query keypoints")
    parser.add_argument("--outliers2d", type=int, default=200, help="random outlier keypoints per query")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    samples = [random_sample(rng, args.points3d, args.detected, args.outliers2d) for _ in range(args.samples)]
    write_dataset(args.out, samples, protocol={"generator": "gomatch_train.synthetic", **vars(args)})
    matched = sum(int((s[2] >= 0).sum()) for s in samples)
    print(f"wrote {args.out}: {len(samples)} samples, {matched} GT matches")


if __name__ == "__main__":
    main()
