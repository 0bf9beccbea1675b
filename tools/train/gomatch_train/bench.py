"""Training throughput: forward + loss + backward per sample, for model configs and point budgets.

    python -m gomatch_train.bench --threads 1 2 --points 256 512 --configs 128x12x4 64x6x4

A config is "<feature_dim>x<encoder_blocks>x<classifier_blocks>". Each measurement uses a synthetic sample with
`points` query keypoints and `points` database points, half of them GT matches (the training outlier rate), and
reports the median over `--repeats` steps after 2 warm-up steps.
"""

import argparse
import statistics
import time

import numpy as np
import torch

from .config import ModelConfig
from .loss import classifier_labels, classifier_loss, match_loss
from .model import GoMatch
from .runtime import keep_freed_memory


def parse_config(text: str) -> ModelConfig:
    d, enc, cls = (int(v) for v in text.split("x"))
    return ModelConfig(feature_dim=d, encoder_blocks=enc, classifier_blocks=cls)


def bench_sample(points: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts2d = torch.from_numpy(rng.uniform(-0.6, 0.6, (points, 2)).astype(np.float32))
    pts3d = torch.from_numpy(rng.uniform(-0.6, 0.6, (points, 2)).astype(np.float32))
    match = np.full(points, -1, dtype=np.int64)
    inliers = points // 2
    match[:inliers] = rng.permutation(points)[:inliers]
    return pts2d, pts3d, torch.from_numpy(match)


def train_step_seconds(model: GoMatch, sample, repeats: int) -> float:
    pts2d, pts3d, match = sample
    times = []
    for i in range(repeats + 2):
        start = time.perf_counter()
        result = model(pts2d, pts3d)
        loss = match_loss(result.log_plan, match) + classifier_loss(
            result.cls_logits, classifier_labels(result.i3d, result.i2d, match)
        )
        loss.backward()
        if i >= 2:
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--points", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--configs", nargs="+", default=["128x12x4", "96x6x4", "64x6x4", "64x4x2"])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    keep_freed_memory()
    torch.manual_seed(0)
    print("| config (d x enc x cls) | params | points | threads | ms / sample | samples/s |")
    print("|---|---|---|---|---|---|")
    for text in args.configs:
        model = GoMatch(parse_config(text))
        params = sum(p.numel() for p in model.parameters())
        for points in args.points:
            sample = bench_sample(points)
            for threads in args.threads:
                torch.set_num_threads(threads)
                seconds = train_step_seconds(model, sample, args.repeats)
                print(f"| {text} | {params} | {points} | {threads} | {seconds * 1e3:.0f} | {1 / seconds:.2f} |", flush=True)


if __name__ == "__main__":
    main()
