"""Training throughput of whole trainer steps on full sets: `tools/train/bench_train.sh WIDTH ENCODER_BLOCKS POINTS`.

    python -m gomatch_train.bench_train 128 12 256 [--steps 6 --warmup 6] [trainer options ...]

Builds synthetic samples that the trainer's subsampling (outlier rate 0.5, `--max-points POINTS`) turns into full
sets of POINTS keypoints and POINTS 3D points, then runs the trainer's own step (`Run.train_batch`: forward and
losses per sample, backward, the workers' gradient sum, Adam) on `--batch` samples per step, in the trainer's
processes (`--workers`, `--threads`). Defaults are the paper-size runs' stages (`stage.sh`, their `run.json`
`trainer_options`): `--workers 2 --threads 1 --compile --bf16 --batch 32`; any trainer option after the three numbers
overrides them (e.g. `--no-bf16`, as the narrow device runs train, or `--workers 1 --threads 2`).
The first `--warmup` steps are not timed (compilation, and matrix kernels made for the first shapes: the
processes reach their steady rate after a few steps). Prints one line per timed step, the CPU time per sample (all
processes; the better figure on a busy machine) and, last, `samples/s: X` (wall time).
"""

import argparse
import os
import resource
import sys
import time

import numpy as np
import torch

from .dataset import Sample
from .parallel import Group, launch
from .synthetic import random_sample
from .train import Run, configure_cpu, epoch_samples, parse_args
from . import compiled

PAPER_STAGE_SETTINGS = ["--workers", "2", "--threads", "1", "--compile", "--bf16", "--batch", "32"]
DISTINCT_SAMPLES = 16


def bench_samples(points: int, seed: int = 0) -> list:
    """Samples with about `points` inliers, `points` 2-D outliers and 3 * `points` 3-D outliers: after the 0.5
    outlier-rate cap and the point budget, both sets hold `points` points."""
    rng = np.random.default_rng(seed)
    return [Sample(*random_sample(rng, 4 * points, points, points), f"bench/q{i}/v0") for i in range(DISTINCT_SAMPLES)]


def measure(args, group: Group = Group()) -> None:
    configure_cpu(args.threads)
    if args.compile:
        compiled.enable()
    run = Run(args)
    drawn = []
    epoch = 0
    needed = (args.warmup + args.steps) * args.batch
    while len(drawn) < needed:
        drawn += epoch_samples(args.samples, epoch, args)
        epoch += 1
    sizes = sorted({(len(p[0]), len(p[1])) for p in drawn})
    batches = [drawn[i * args.batch : (i + 1) * args.batch] for i in range(args.warmup + args.steps)]
    for batch in batches[: args.warmup]:
        run.train_batch(batch, group)
    group.sum_(torch.zeros(1))  # every process has finished warming up
    start, start_cpu = time.perf_counter(), time.process_time()
    for i, batch in enumerate(batches[args.warmup :]):
        step_start = time.perf_counter()
        run.train_batch(batch, group)
        if group.is_main:
            print(f"step {i}: {time.perf_counter() - step_start:.3f} s", flush=True)
    wall = time.perf_counter() - start
    cpu = group.sum_(torch.tensor([time.process_time() - start_cpu], dtype=torch.float64)).item()
    if group.is_main:
        samples = args.steps * args.batch
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"set sizes (keypoints, 3D points): {sizes[0]}..{sizes[-1]}; {args.workers} worker(s) x "
              f"{args.threads} thread(s), batch {args.batch}, compile {args.compile}, bf16 {args.bf16}; "
              f"load average {os.getloadavg()[0]:.1f}; peak RSS of the main process {peak_mb:.0f} MB")  # fmt: skip
        print(f"CPU per sample: {1e3 * cpu / samples:.1f} ms (all processes)")
        print(f"samples/s: {samples / wall:.2f}", flush=True)


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("width", type=int)
    p.add_argument("encoder_blocks", type=int)
    p.add_argument("points", type=int)
    p.add_argument("--steps", type=int, default=6, help="timed optimizer steps")
    p.add_argument("--warmup", type=int, default=6,
                   help="untimed steps first (compilation, and matrix kernels made for the first shapes)")
    ours, trainer_options = p.parse_known_args(argv)
    args = parse_args(
        ["--train", "-", "--val", "-", "--out", os.devnull, "--feature-dim", str(ours.width),
         "--encoder-blocks", str(ours.encoder_blocks), "--max-points", str(ours.points), *PAPER_STAGE_SETTINGS,
         *trainer_options]
    )  # fmt: skip
    args.steps, args.warmup = ours.steps, ours.warmup
    args.samples = bench_samples(ours.points)
    launch(measure, args, args.workers)


if __name__ == "__main__":
    main()
