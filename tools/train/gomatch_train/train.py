"""Train GoMatch (BVs) on `gomatch-dataset` files.

    python -m gomatch_train.train --train A.safetensors [B.safetensors ...] --val V.safetensors --out DIR \
        --epochs 20 --batch 16 --max-points 256 --workers 2 [--feature-dim 64 --encoder-blocks 6] [--resume]

One forward pass per sample (InstanceNorm statistics are per set and set sizes differ); gradients of `--batch`
samples are accumulated (mean loss) before each Adam step, optionally shared among `--workers` processes.
`--batched` (for the GPU) instead runs one forward pass per batch: samples are grouped by size and cropped to the
smallest set sizes of their batch (see `equal_size_batches`). Every
epoch draws a fresh subsample of every training sample (outlier rate and point budget, see dataset.py) from a
generator seeded by (seed, epoch, sample), so a run resumed from a checkpoint repeats exactly what the uninterrupted
run would have done. `--init MODEL` starts a new run (fresh optimizer, epoch 0) from an export's weights: a
fine-tuning stage, e.g. with another `--outlier-rate`.

Files in DIR:
    checkpoint.pt       model, optimizer, position (epoch, batch), RNG states, history; every epoch and every
                        --ckpt-minutes; --resume continues from it
    last.safetensors    export of the latest checkpointed model (export.py format)
    best.safetensors    export of the model with the lowest validation loss so far
    history.jsonl       one JSON line of validation metrics per epoch
"""

import argparse
import json
import os
import random
import sys
import time

import numpy as np
import torch

from . import compiled, run_state
from .config import ModelConfig
from .dataset import load_samples, subsample
from .encoder import matrices_per_step
from .evaluate import Totals, assess, assess_batch
from .export import load_export, save_export
from .model import GoMatch
from .parallel import Group, launch
from .runtime import configure_cpu

CHECKPOINT = "checkpoint.pt"
# Options that must not change when a run is resumed (they define what the run computes).
FIXED_ON_RESUME = (
    "train", "val", "seed", "batch", "lr", "max_points", "min_points", "outlier_rate", "val_max_points",
    "feature_dim", "encoder_blocks", "classifier_blocks", "heads", "sinkhorn_iters", "init", "continue_from", "batched",
    "teacher", "distill_weight",
)  # fmt: skip
NO_OUTLIER_CONTROL = (0.0, 1.0)  # outlier-rate range that keeps every point (the paper's tests)
VAL_MIN_POINTS = 10  # reference: evaluation counts a sample as failed below 10 points; no other filtering


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--train", nargs="+", required=True, help="training dataset file(s)")
    p.add_argument("--val", required=True, help="validation dataset file")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch", type=int, default=16, help="samples per optimizer step (gradient accumulation)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--max-points", type=int, default=256, help="point budget per set and sample (<= 0: none)")
    p.add_argument("--min-points", type=int, default=100, help="skip training samples with a smaller set")
    p.add_argument("--outlier-rate", type=float, nargs=2, default=[0.5, 0.5], metavar=("LOW", "HIGH"),
                   help="keypoint outlier rate range enforced on training samples (reference: 0.5 0.5)")
    p.add_argument("--val-max-points", type=int, default=None, help="validation point budget (default --max-points)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads per worker")
    p.add_argument("--workers", type=int, default=1, help="data-parallel processes sharing each batch")
    p.add_argument("--batched", action="store_true",
                   help="one forward pass per batch of equal-size samples (cropped to the batch's smallest sets)")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the hot functions of the training step (CPU: about 1.6x faster; compiles "
                        "for a minute first)")
    p.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=False,
                   help="bfloat16 autocast for the network's matrix products (the matching layer, every "
                        "normalisation and, below 512 points per set, the attention stay float32)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--feature-dim", type=int, default=ModelConfig.feature_dim)
    p.add_argument("--encoder-blocks", type=int, default=ModelConfig.encoder_blocks)
    p.add_argument("--classifier-blocks", type=int, default=ModelConfig.classifier_blocks)
    p.add_argument("--heads", type=int, default=ModelConfig.heads, help="cross-attention heads")
    p.add_argument("--sinkhorn-iters", type=int, default=ModelConfig.sinkhorn_iters, help="maximum Sinkhorn iterations")
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt when it exists")
    p.add_argument("--init", default=None, metavar="MODEL",
                   help="start a new run from the weights of this export (a fine-tuning stage; same configuration)")
    p.add_argument("--continue", dest="continue_from", default=None, metavar="STATE",
                   help="start from a staged run's state (run_state.py: weights and Adam state) on new data")
    p.add_argument("--teacher", default=None, metavar="MODEL",
                   help="export of a trained model whose Sinkhorn plans the run distils (loss.distillation_loss)")
    p.add_argument("--distill-weight", type=float, default=1.0, help="weight of the distillation loss (--teacher)")
    p.add_argument("--max-minutes", type=float, default=None, help="checkpoint and stop after this wall time")
    p.add_argument("--max-steps", type=int, default=None, help="checkpoint and stop after this many optimizer steps")
    p.add_argument("--ckpt-minutes", type=float, default=10.0, help="checkpoint interval within an epoch")
    p.add_argument("--log-every", type=int, default=10, help="print training progress every N optimizer steps")
    args = p.parse_args(argv)
    if args.val_max_points is None:
        args.val_max_points = args.max_points
    if args.batch < 1 or args.epochs < 0 or args.workers < 1:
        p.error("--batch and --workers must be >= 1 and --epochs >= 0")
    if args.workers > 1 and args.device != "cpu":
        p.error("--workers > 1 is for CPU training")
    return args


def model_config(args) -> ModelConfig:
    return ModelConfig(
        feature_dim=args.feature_dim,
        encoder_blocks=args.encoder_blocks,
        classifier_blocks=args.classifier_blocks,
        heads=args.heads,
        sinkhorn_iters=args.sinkhorn_iters,
    )


def to_tensors(prepared, device):
    pts2d, pts3d, match = prepared
    return (
        torch.from_numpy(np.ascontiguousarray(pts2d)).to(device),
        torch.from_numpy(np.ascontiguousarray(pts3d)).to(device),
        torch.from_numpy(np.ascontiguousarray(match)).to(device),
    )


def stacked_tensors(samples: list, device):
    """(B, N2, 2), (B, N3, 2), (B, N2) tensors of equal-size subsampled samples."""
    return to_tensors(tuple(np.stack(parts) for parts in zip(*samples)), device)


def epoch_samples(samples: list, epoch: int, args) -> list:
    """This epoch's subsampled training samples in random order, a pure function of (seed, epoch)."""
    order = np.random.default_rng([args.seed, epoch]).permutation(len(samples))
    prepared = []
    for index in order:
        rng = np.random.default_rng([args.seed, epoch, int(index)])
        drawn = subsample(samples[index], rng, tuple(args.outlier_rate), args.max_points, args.min_points)
        if drawn is not None:
            prepared.append(drawn)
    return prepared


def epoch_batches(prepared: list, epoch: int, args) -> list:
    """The batches of one epoch's samples (`epoch_samples`), also a pure function of (seed, epoch)."""
    if args.batched:
        return equal_size_batches(prepared, args.batch, np.random.default_rng([args.seed, epoch, len(prepared)]))
    return [prepared[i : i + args.batch] for i in range(0, len(prepared), args.batch)]


def point_count(prepared: list) -> int:
    """Keypoints plus 3D points of subsampled samples."""
    return sum(len(pts2d) + len(pts3d) for pts2d, pts3d, _ in prepared)


def equal_size_batches(prepared: list, batch: int, rng: np.random.Generator) -> list:
    """Batches whose samples have equal set sizes, for one batched forward pass.

    Samples are sorted by (N2, N3) (stably, so equal sizes keep their random order) and cut into batches; each
    sample is cropped to the smallest N2 and N3 of its batch. Both sets are randomly permuted (`subsample`), so a
    crop keeps a random subset; a keypoint whose 3D point is cropped becomes unmatched. Batches come in random order.
    """
    order = sorted(range(len(prepared)), key=lambda i: (len(prepared[i][0]), len(prepared[i][1])))
    batches = []
    for start in range(0, len(order), batch):
        members = [prepared[i] for i in order[start : start + batch]]
        n2d, n3d = min(len(m[0]) for m in members), min(len(m[1]) for m in members)
        batches.append([crop(m, n2d, n3d) for m in members])
    return [batches[i] for i in rng.permutation(len(batches))]


def crop(prepared, n2d: int, n3d: int):
    """The first n2d keypoints and n3d 3D points of a subsampled sample, with the matches that remain."""
    pts2d, pts3d, match = prepared
    match = match[:n2d].copy()
    match[match >= n3d] = -1
    return pts2d[:n2d], pts3d[:n3d], match


def validation_set(
    samples: list, seed: int, max_points: int, outlier_rate=NO_OUTLIER_CONTROL, scene: str | None = None
) -> list:
    """Validation samples, subsampled once (at most `max_points` per set; by default no outlier control, as the
    paper's tests), optionally only those of one scene (the others do not change which points are drawn)."""
    prepared = []
    for index, sample in enumerate(samples):
        if scene is not None and not sample.name.startswith(scene + "/"):
            continue
        drawn = validation_draw(sample, index, seed, max_points, outlier_rate)
        if drawn is not None:
            prepared.append(drawn)
    return prepared


def validation_draw(sample, index: int, seed: int, max_points: int, outlier_rate=NO_OUTLIER_CONTROL):
    """The validation subsample of the `index`-th sample of a file (the same for every run with `seed`), or None."""
    rng = np.random.default_rng([seed, 1_000_003, index])
    return subsample(sample, rng, tuple(outlier_rate), max_points, VAL_MIN_POINTS)


@torch.no_grad()
def validate(model: GoMatch, val: list, device, group: Group = Group()) -> dict:
    model.eval()
    totals = Totals()
    for prepared in group.share(val):
        pts2d, pts3d, match = to_tensors(prepared, device)
        totals.add(assess(model(pts2d, pts3d), match, model.config.match_threshold))
    model.train()
    return Totals.from_tensor(group.sum_(totals.to_tensor())).summary()


def rng_states() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def restore_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])


def atomic_save(obj, path: str) -> None:
    tmp = path + ".tmp"
    torch.save(obj, tmp)
    os.replace(tmp, path)


def atomic_export(model: GoMatch, path: str) -> None:
    tmp = path + ".tmp"
    save_export(model, tmp)
    os.replace(tmp, path)


def load_teacher(path: str, device) -> GoMatch:
    """A frozen model to distil (`--teacher`): any configuration, in inference mode."""
    teacher = load_export(path).to(device).eval()
    teacher.requires_grad_(False)
    return teacher


class Run:
    """Model, optimizer and position of one training run, with checkpointing."""

    def __init__(self, args):
        self.args = args
        self.device = torch.device(args.device)
        self.out = args.out
        self.checkpoint_path = os.path.join(args.out, CHECKPOINT)
        self.epoch = 0
        self.next_batch = 0
        self.step = 0
        self.best_val_loss = float("inf")
        self.history = []
        torch.manual_seed(args.seed)
        np.random.seed(args.seed)
        random.seed(args.seed)
        self.model = GoMatch(model_config(args)).to(self.device)
        if args.init is not None:
            self.start_from(args.init)
        self.teacher = load_teacher(args.teacher, self.device) if args.teacher is not None else None
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=args.lr, fused=True)
        self.samples = 0  # samples trained on in this run
        self.totals = Totals()  # training losses and counts of this process since the run (or resume) started
        if args.continue_from is not None:
            self.continue_from(args.continue_from)

    def continue_from(self, path: str) -> None:
        """Weights and Adam state of a staged run (`run_state.py`), whose configuration must be this run's."""
        state = run_state.load(path)
        weights, optimizer_state, _ = run_state.unpack(state)
        config = run_state.config_of(state)
        if config != self.model.config:
            raise SystemExit(f"--continue {path}: configuration {config.to_json()} differs from this run's "
                             f"{self.model.config.to_json()}")  # fmt: skip
        self.model.load_state_dict(weights)
        for group in optimizer_state["param_groups"]:
            group["lr"] = self.args.lr
        self.optimizer.load_state_dict(optimizer_state)

    def start_from(self, path: str) -> None:
        """Initial weights from an export, whose configuration must be this run's."""
        initial = load_export(path)
        if initial.config != self.model.config:
            raise SystemExit(f"--init {path}: configuration {initial.config.to_json()} differs from this run's "
                             f"{self.model.config.to_json()}")  # fmt: skip
        self.model.load_state_dict(initial.state_dict())

    def fixed_options(self) -> dict:
        return {name: getattr(self.args, name) for name in FIXED_ON_RESUME}

    def save(self) -> None:
        state = {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "epoch": self.epoch,
            "next_batch": self.next_batch,
            "step": self.step,
            "samples": self.samples,
            "train_totals": self.totals.summary() if self.totals.samples else {},
            "best_val_loss": self.best_val_loss,
            "history": self.history,
            "options": self.fixed_options(),
            "config": self.model.config.to_json(),
            "rng": rng_states(),
        }
        atomic_save(state, self.checkpoint_path)
        atomic_export(self.model, os.path.join(self.out, "last.safetensors"))

    def load(self) -> None:
        state = torch.load(self.checkpoint_path, map_location=self.device, weights_only=False)
        mine = self.fixed_options()
        changed = {k: (v, mine.get(k)) for k, v in state["options"].items() if mine.get(k) != v}
        if changed:
            details = ", ".join(
                f"--{k.replace('_', '-')}: checkpoint {a!r}, now {b!r}" for k, (a, b) in changed.items()
            )
            raise SystemExit(f"cannot resume {self.checkpoint_path}: options differ ({details})")
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.epoch = state["epoch"]
        self.next_batch = state["next_batch"]
        self.step = state["step"]
        self.samples = state.get("samples", 0)
        self.best_val_loss = state["best_val_loss"]
        self.history = state["history"]
        restore_rng_states(state["rng"])

    def train_batch(self, batch: list, group: Group) -> Totals:
        """One Adam step on the mean loss of `batch`; this process computes its share (per sample, or in one
        batched pass with --batched). Returns its totals."""
        self.optimizer.zero_grad(set_to_none=True)
        totals = Totals()
        with matrices_per_step(self.model):
            for chunk in self.forward_chunks(group.share(batch)):
                outcomes = self.assess_chunk(chunk)
                (sum(outcome.loss for outcome in outcomes) / len(batch)).backward()
                for outcome in outcomes:
                    totals.add(outcome)
        group.sum_gradients(self.model.parameters())
        self.optimizer.step()
        return totals

    def forward_chunks(self, share: list) -> list:
        """This process's share of a batch, cut into the sample groups of one forward pass each."""
        if self.args.batched:
            return [share] if share else []
        return [[prepared] for prepared in share]

    def assess_chunk(self, chunk: list) -> list:
        """Outcomes of one forward pass over equal-size samples."""
        pts2d, pts3d, match = stacked_tensors(chunk, self.device)
        threshold = self.model.config.match_threshold
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.args.bf16):
            result = self.model.forward_batch(pts2d, pts3d)
            if self.teacher is None:
                return assess_batch(result, match, threshold)
            with torch.no_grad():
                taught = self.teacher.forward_batch(pts2d, pts3d)
        return assess_batch(result, match, threshold, taught, self.args.distill_weight)


def train(args, group: Group = Group()) -> dict:
    """Run (or resume) training as process `group.rank` of `group.world`; returns the last validation summary
    (empty if none ran). Only the main process prints and writes files."""

    def log(message: str) -> None:
        if group.is_main:
            print(message, flush=True)

    configure_cpu(args.threads)
    if args.compile:
        compiled.enable()
    os.makedirs(args.out, exist_ok=True)
    run = Run(args)
    if args.resume and os.path.exists(run.checkpoint_path):
        run.load()
        log(f"resumed {run.checkpoint_path}: epoch {run.epoch}, batch {run.next_batch}, step {run.step}")
    elif args.resume:
        log(f"no checkpoint in {args.out}; starting a new run")

    samples = [s for path in args.train for s in load_samples(path)]
    val = validation_set(load_samples(args.val), args.seed, args.val_max_points)
    params = sum(p.numel() for p in run.model.parameters())
    log(f"model {run.model.config.to_json()} ({params} parameters); {len(samples)} training samples, "
        f"{len(val)} validation samples")  # fmt: skip
    log(f"Adam lr {args.lr:g}, batch {args.batch}, outlier rate {args.outlier_rate[0]:g}-{args.outlier_rate[1]:g}, "
        f"at most {args.max_points} points per set")  # fmt: skip

    if not val:
        raise SystemExit(f"no validation sample in {args.val} has >= {VAL_MIN_POINTS} points in both sets")
    summary = run.history[-1] if run.history else {}
    if args.max_steps is not None and run.step >= args.max_steps:
        log(f"step limit {args.max_steps} already reached (step {run.step}); nothing to do")
        return summary
    start = last_ckpt = time.monotonic()
    while run.epoch < args.epochs:
        drawn = epoch_samples(samples, run.epoch, args)
        batches = epoch_batches(drawn, run.epoch, args)
        if not batches:
            raise SystemExit(f"no training sample has >= {args.min_points} points after subsampling")
        if run.next_batch == 0:
            crops = ""
            if args.batched:
                kept = sum(point_count(batch) for batch in batches) / point_count(drawn)
                crops = f", {100 * kept:.2f} % of their points kept by the equal-size crops"
            log(f"epoch {run.epoch}: {len(drawn)} samples in {len(batches)} batches{crops}")
        window, window_start = Totals(), time.monotonic()
        while run.next_batch < len(batches):
            batch_totals = run.train_batch(batches[run.next_batch], group)
            window.merge(batch_totals)
            run.totals.merge(batch_totals)
            run.samples += len(batches[run.next_batch])
            run.next_batch += 1
            run.step += 1
            now = time.monotonic()
            if run.step % args.log_every == 0 or run.next_batch == len(batches):
                window = Totals.from_tensor(group.sum_(window.to_tensor()))
                s = window.summary()
                distilled = f", distil {s['distill_loss']:.4f}" if args.teacher else ""
                log(f"epoch {run.epoch} batch {run.next_batch}/{len(batches)} step {run.step}: "
                    f"loss {s['loss']:.4f} (match {s['match_loss']:.4f}, cls {s['cls_loss']:.4f}{distilled}) "
                    f"match P/R {s['match_precision']:.3f}/{s['match_recall']:.3f} "
                    f"{window.samples / max(now - window_start, 1e-9):.2f} samples/s, "
                    f"{(now - start) / 60:.1f} min, {time.process_time() / 60:.1f} CPU min")  # fmt: skip
                window, window_start = Totals(), now
            out_of_time = args.max_minutes is not None and now - start >= args.max_minutes * 60
            out_of_steps = args.max_steps is not None and run.step >= args.max_steps
            checkpoint_due = now - last_ckpt >= args.ckpt_minutes * 60
            out_of_time, checkpoint_due = group.agree([out_of_time, checkpoint_due])
            if out_of_time or out_of_steps or checkpoint_due:
                if group.is_main:
                    run.save()
                last_ckpt = now
                if out_of_time or out_of_steps:
                    log(f"stopping at step {run.step} ({'time' if out_of_time else 'step'} limit); checkpoint saved")
                    return summary

        summary = validate(run.model, val, run.device, group)
        summary["epoch"] = run.epoch
        summary["step"] = run.step
        improved = summary["loss"] < run.best_val_loss
        log(f"epoch {run.epoch} validation: loss {summary['loss']:.4f} (match {summary['match_loss']:.4f}, "
            f"cls {summary['cls_loss']:.4f}) match P/R {summary['match_precision']:.3f}/"
            f"{summary['match_recall']:.3f} cls P/R@{run.model.config.match_threshold} "
            f"{summary['cls_precision']:.3f}/{summary['cls_recall']:.3f}"
            f"{' (best)' if improved else ''}")  # fmt: skip
        if improved:
            run.best_val_loss = summary["loss"]
            if group.is_main:
                atomic_export(run.model, os.path.join(args.out, "best.safetensors"))
        run.history.append(summary)
        run.epoch += 1
        run.next_batch = 0
        if group.is_main:
            run.save()
            with open(os.path.join(args.out, "history.jsonl"), "w") as f:
                f.writelines(json.dumps(entry) + "\n" for entry in run.history)
        last_ckpt = time.monotonic()
    return summary


def main(argv=None) -> None:
    args = parse_args(argv)
    launch(train, args, args.workers)


if __name__ == "__main__":
    sys.exit(main())
