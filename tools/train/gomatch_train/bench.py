"""Training throughput: forward + loss + backward per sample, for model configs and point budgets.

    python -m gomatch_train.bench --threads 1 2 --points 256 512 --configs 128x12x4 64x6x4

A config is "<feature_dim>x<encoder_blocks>x<classifier_blocks>". Each measurement uses a synthetic sample with
`points` query keypoints and `points` database points, half of them GT matches (the training outlier rate), and
reports, over `--repeats` steps after 2 warm-up steps, the fastest and the median wall time and the median process
CPU time, with the 1-minute load average when the row was measured. On a shared machine the wall time includes time
spent waiting for a core; with one thread the CPU time is the better estimate of the uncontended step time.

    python -m gomatch_train.bench --batching --threads 1

compares, for the encoder alone, 16 samples processed one at a time with 16 equal-sized samples processed as one
batched tensor: the most that batching same-sized samples could save.
"""

import argparse
import os
import statistics
import time

import numpy as np
import torch

from .config import ModelConfig
from .encoder import PointResNet
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


def timed(step, repeats: int):
    """(fastest wall, median wall, median CPU) seconds of `repeats` calls of `step` after 2 warm-up calls."""
    wall, cpu = [], []
    for i in range(repeats + 2):
        start, start_cpu = time.perf_counter(), time.process_time()
        step()
        if i >= 2:
            wall.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
    return min(wall), statistics.median(wall), statistics.median(cpu)


def train_step(model: GoMatch, sample) -> None:
    pts2d, pts3d, match = sample
    result = model(pts2d, pts3d)
    loss = match_loss(result.log_plan, match) + classifier_loss(
        result.cls_logits, classifier_labels(result.i3d, result.i2d, match)
    )
    loss.backward()


def batching_report(threads: int, repeats: int) -> None:
    torch.set_num_threads(threads)
    encoder = PointResNet(2, 128, 12)
    points = torch.rand(16, 256, 2)
    one_by_one = timed(lambda: [encoder(p).sum().backward() for p in points], repeats)
    batched = timed(lambda: encoder(points).sum().backward(), repeats)
    print(f"encoder (128 wide, 12 blocks) forward+backward of 16 samples x 256 points, {threads} thread(s):")
    for name, (fastest, median, cpu) in (("one sample at a time", one_by_one), ("one batched tensor  ", batched)):
        print(f"  {name}: wall fastest {fastest * 1e3:.0f} ms, median {median * 1e3:.0f} ms; CPU {cpu * 1e3:.0f} ms")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--points", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--configs", nargs="+", default=["128x12x4", "96x6x4", "64x6x4", "64x4x2"])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--batching", action="store_true", help="encoder: per-sample loop vs batched tensor")
    args = parser.parse_args(argv)
    keep_freed_memory()
    torch.manual_seed(0)
    if args.batching:
        for threads in args.threads:
            batching_report(threads, args.repeats)
        return
    print("| config (d x enc x cls) | params | points | threads | wall fastest ms | wall median ms | CPU ms | load |")
    print("|---|---|---|---|---|---|---|---|")
    for text in args.configs:
        model = GoMatch(parse_config(text))
        params = sum(p.numel() for p in model.parameters())
        for points in args.points:
            sample = bench_sample(points)
            for threads in args.threads:
                torch.set_num_threads(threads)
                fastest, median, cpu = timed(lambda: train_step(model, sample), args.repeats)
                load = os.getloadavg()[0]
                print(
                    f"| {text} | {params} | {points} | {threads} | {fastest * 1e3:.0f} | {median * 1e3:.0f} "
                    f"| {cpu * 1e3:.0f} | {load:.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
