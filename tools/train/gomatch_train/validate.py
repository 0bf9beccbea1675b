"""Evaluate an exported model on a dataset file: the trainer's validation metrics.

    python -m gomatch_train.validate MODEL.safetensors DATA.safetensors [--max-points 256] [--seed 0] [--threads 1]
        [--scene colmap/sceaux] [--outlier-rate LOW HIGH]

Samples are subsampled as the trainer's validation set (no outlier control, at most --max-points per set; the same
--seed gives the same subsample as a training run with that seed). `--scene` keeps one scene's samples;
`--outlier-rate` controls the outlier rate as the trainer does (diagnostics: how matching depends on it).
Besides the trainer's metrics it prints `keypoint_inlier_rate`, the mean share of query keypoints with a match.
"""

import argparse
import json

import numpy as np

from .dataset import load_samples
from .export import load_export
from .runtime import configure_cpu
from .train import NO_OUTLIER_CONTROL, VAL_MIN_POINTS, validate, validation_set


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model")
    p.add_argument("data")
    p.add_argument("--max-points", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--scene", default=None, help="only the samples of this scene (e.g. colmap/sceaux)")
    p.add_argument("--outlier-rate", type=float, nargs=2, default=list(NO_OUTLIER_CONTROL), metavar=("LOW", "HIGH"),
                   help="outlier-rate range as in training (default: no control)")
    args = p.parse_args(argv)
    configure_cpu(args.threads)
    model = load_export(args.model).to(args.device)
    val = validation_set(load_samples(args.data), args.seed, args.max_points, args.outlier_rate, args.scene)
    if not val:
        raise SystemExit(f"no sample of {args.data} (scene {args.scene!r}) has >= {VAL_MIN_POINTS} points in both sets")
    summary = validate(model, val, args.device)
    summary["keypoint_inlier_rate"] = float(np.mean([(match >= 0).mean() for _, _, match in val]))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
