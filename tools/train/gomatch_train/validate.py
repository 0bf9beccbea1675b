"""Evaluate an exported model on a dataset file: the trainer's validation metrics.

    python -m gomatch_train.validate MODEL.safetensors DATA.safetensors [--max-points 256] [--seed 0] [--threads 1]

Samples are subsampled as the trainer's validation set (no outlier control, at most --max-points per set; the same
--seed gives the same subsample as a training run with that seed).
"""

import argparse
import json

from .dataset import load_samples
from .export import load_export
from .runtime import configure_cpu
from .train import validate, validation_set


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model")
    p.add_argument("data")
    p.add_argument("--max-points", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = p.parse_args(argv)
    configure_cpu(args.threads)
    model = load_export(args.model).to(args.device)
    val = validation_set(load_samples(args.data), args.seed, args.max_points)
    print(json.dumps(validate(model, val, args.device), indent=1))


if __name__ == "__main__":
    main()
