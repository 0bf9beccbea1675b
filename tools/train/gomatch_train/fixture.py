"""Write one forward pass of our model in the reference fixture layout (shared/reference/README.md).

The Rust side reads this layout with `gomatch-sim conform --fixture DIR --weights W`, so the same weights and inputs
can be run through both implementations and compared stage by stage:

    python -m gomatch_train.fixture WEIGHTS.safetensors OUT_DIR --points 200 150 --seed 0
"""

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from .export import load_export
from .model import GoMatch
from .synthetic import random_sample

ATTENTION_STAGES = ("att0_self", "att1_cross", "att2_self")


def forward_stages(model: GoMatch, pts2d: torch.Tensor, pts3d: torch.Tensor) -> tuple[dict, int]:
    """Name -> array of every stage the reference fixtures record, and the Sinkhorn iterations run."""
    raw = model.matcher.raw_matcher
    encoded, attended = [], []
    hooks = [raw.kp2d_enc.register_forward_hook(lambda m, i, o: encoded.append(o))]
    hooks += [layer.register_forward_hook(lambda m, i, o: attended.append(o)) for layer in raw.attention.att.layers]
    try:
        with torch.no_grad():
            result = model(pts2d, pts3d)
    finally:
        for hook in hooks:
            hook.remove()
    stages = {"pts2d": pts2d, "pts3d_bvs": pts3d, "enc2d": encoded[0], "enc3d": encoded[1]}
    for (out2d, out3d), name in zip(attended, ATTENTION_STAGES):
        stages[f"{name}_2d"], stages[f"{name}_3d"] = out2d, out3d
    stages.update(
        desc2d_l2=result.desc2d,
        desc3d_l2=result.desc3d,
        ot_cost=result.cost,
        scores=result.plan,
        match_i3d=result.i3d,
        match_i2d=result.i2d,
        match_probs=result.match_probs,
    )
    return {name: t.detach().cpu().numpy() for name, t in stages.items()}, result.sinkhorn_iterations


def write_fixture(model: GoMatch, pts2d: np.ndarray, pts3d: np.ndarray, out: Path) -> None:
    """Run `model` on one pair and write every stage as .npy plus index.json into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    arrays, iterations = forward_stages(model.eval(), torch.from_numpy(pts2d), torch.from_numpy(pts3d))
    for name, array in arrays.items():
        np.save(out / f"{name}.npy", np.ascontiguousarray(array))
    index = {
        "model": "gomatch_train",
        "config": json.loads(model.config.to_json()),
        "sinkhorn": {"iterations_run": iterations},
        "arrays": {name: {"file": f"{name}.npy", "shape": list(a.shape), "dtype": str(a.dtype)} for name, a in arrays.items()},
    }
    (out / "index.json").write_text(json.dumps(index, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("weights", help="exported safetensors checkpoint")
    parser.add_argument("out", type=Path, help="fixture folder to write")
    parser.add_argument("--points", type=int, nargs=2, default=(200, 150), metavar=("N3D", "N_DETECTED"))
    parser.add_argument("--outliers", type=int, default=60, help="outlier keypoints added to the query")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    pts2d, pts3d, _ = random_sample(np.random.default_rng(args.seed), args.points[0], args.points[1], args.outliers)
    write_fixture(load_export(args.weights), pts2d, pts3d, args.out)


if __name__ == "__main__":
    main()
