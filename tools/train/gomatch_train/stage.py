"""One stage of a staged training run: `tools/train/stage.sh RUN MINUTES` (which builds the Rust tools first).

A run lives in `tools/train/stages/RUN/`, committed with the repository:
    run.json   what the run trains: model size, learning rate, batch, the point budget per part of the run
               (`schedule`), the data of each stage (real training scenes and synthetic scenes), an optional
               model to start from (`init`) and an optional model to distil (`teacher`, `distill_weight`: the
               trainer's `--teacher`, `--distill-weight`); each an export or another run's folder (the weights
               of its committed state)
    state.pt   weights and Adam state after the last stage (run_state.py, ~6 bytes a parameter)
    log.md     one row per stage: samples so far, CPU minutes, samples/s, training loss, validation matching
               and pose accuracy per validation scene at N = 1024 and N = 256 (int8 blob, k = 10)

A stage (1) writes its data: every real training scene of ../shared/data (the validation scenes excluded) with
queries drawn with protocol seed = the stage number, and synthetic scenes (the four layouts and photo
collections) from a synthetic seed no earlier stage used (1000 + stage); (2) continues training from state.pt
(or starts from `init`, or from scratch) for MINUTES with `--compile` on two processes; (3) packs state.pt and
exports the weights; (4) converts the export to an int8 blob and evaluates it on every validation scene at
N = 1024 and 256 (`eval_all.sh`), and runs the trainer's validation metrics; (5) appends the row to log.md.
It does not commit: stage.sh does (`git commit` of the run folder) when it was asked to (`COMMIT=1`).

Everything bulky (data, checkpoints, blobs, reports) goes to a work folder outside the repository
(`$GOMATCH_STAGE_WORK`, default ~/.cache/gomatch-stages/RUN).
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

from . import run_state
from .export import save_export

HERE = Path(__file__).resolve().parents[1]  # tools/train
REPO = HERE.parents[1]
VALIDATION = ["colmap/mouse", "colmap/sceaux", "colmap/mamechun", "colmap/softmurata", "opensfm/projcv_cc9d27"]
SYNTHETIC_SEED_BASE = 1000  # seeds 0-4 are the demo's, the firmware query's and the first GPU runs'
LOG_HEADER = (
    "| stage | samples so far | CPU min so far | points | minutes | samples/s | training loss | "
    "val match P / R | AUC @1/5/10 px, N = 1024 (mouse; sceaux; mamechun; softmurata; projcv) | "
    "AUC @1/5/10 px, N = 256 (same order) |\n|---|---|---|---|---|---|---|---|---|---|\n"
)


def run_command(command: list, log: Path | None = None, **kw) -> None:
    print("+", " ".join(str(c) for c in command), flush=True)
    if log is None:
        subprocess.run(command, check=True, **kw)
        return
    with open(log, "w") as f:
        subprocess.run(command, check=True, stdout=f, stderr=subprocess.STDOUT, **kw)


def scene_arguments(data: Path, split: str) -> list:
    """`gomatch-sim dataset` source options of every scene of the split ("train" or "val")."""
    out = []
    for kind in ("colmap", "opensfm"):
        for folder in sorted((data / kind).iterdir()):
            if folder.is_dir() and ((f"{kind}/{folder.name}" in VALIDATION) == (split == "val")):
                out += [f"--{kind}", str(folder)]
    if split == "train":
        out += [a for f in sorted((data / "bal").glob("*.txt")) for a in ("--bal", str(f))]
        out += [a for f in sorted((data / "bundler").glob("*/bundle.out")) for a in ("--bundler", str(f))]
    return out


def write_data(sim: Path, data: Path, work: Path, stage: int, spec: dict, part: dict) -> list:
    """This stage's training files (real scenes, synthetic layouts and collections), written in parallel, with the
    keypoint and view-point caps of the run part's `data_capacity` (`gomatch-sim dataset --capacity`; its default
    without)."""
    capacity = capacity_arguments(part)
    jobs = {
        "real": [*scene_arguments(data, "train"), "--queries-per-scene", str(spec["real_queries_per_scene"]),
                 "--seed", str(stage)],
        "synthetic": ["--synthetic", str(spec["synthetic_scenes"]), "--synthetic-collection",
                      str(spec["collection_scenes"]), "--synthetic-seed", str(SYNTHETIC_SEED_BASE + stage)],
    }  # fmt: skip
    processes = []
    for name, options in jobs.items():
        out = work / f"{name}.safetensors"
        log = open(work / f"data-{name}.log", "w")
        command = [sim, "dataset", "--output", out, *options, *capacity]
        processes.append((subprocess.Popen(command, stdout=log, stderr=log), out))
    for process, _ in processes:
        if process.wait() != 0:
            raise SystemExit(f"gomatch-sim dataset failed (logs in {work})")
    return [out for _, out in processes]


def capacity_arguments(part: dict) -> list:
    """`gomatch-sim dataset` options for the caps of the run part's `data_capacity` (the tool's default without)."""
    return ["--capacity", str(part["data_capacity"])] if "data_capacity" in part else []


def validation_file(cache: Path, part: dict) -> Path:
    """Where a run keeps its validation samples with the part's data caps (one file per caps)."""
    return cache / (f"val-caps{part['data_capacity']}.safetensors" if "data_capacity" in part else "val.safetensors")


def validation_data(sim: Path, data: Path, cache: Path, part: dict) -> Path:
    """The validation scenes' samples (20 queries each, protocol seed 0) with the same caps as the part's training
    data, so that the trainer's validation and the log's match precision and recall measure the distribution the
    part trains for; written once per run and caps."""
    out = validation_file(cache, part)
    if not out.exists():
        run_command([sim, "dataset", "--output", out, *scene_arguments(data, "val"), "--queries-per-scene", "20",
                     *capacity_arguments(part)], cache / f"data-{out.stem}.log")  # fmt: skip
    return out


def part_for(schedule: list, samples: int) -> dict:
    """The part of the schedule the run is in: its point budget (`max_points`), optional training outlier-rate
    range (`outlier_rate`: [LOW, HIGH], the trainer's `--outlier-rate`; the trainer's default 0.5-0.5 without) and
    optional caps of its data (`data_capacity`: the localizer capacity whose caps the samples get; 1024 without)."""
    for part in schedule:
        if "until_samples" not in part or samples < part["until_samples"]:
            return part
    return schedule[-1]


def budget_cell(part: dict) -> str:
    """The log's "points" cell: the point budget, a non-default outlier-rate range and data caps."""
    rate, caps = part.get("outlier_rate"), part.get("data_capacity")
    return (f"{part['max_points']}" + (f", outliers {rate[0]:g}-{rate[1]:g}" if rate else "")
            + (f", caps {caps}" if caps else ""))  # fmt: skip


def export_of(source: str, out: Path) -> Path:
    """The export a run's `init` or `teacher` names: a safetensors file of the repository, or a run folder
    (tools/train/stages/RUN), whose committed state's weights are exported to `out`."""
    path = REPO / source
    if not path.is_dir():
        return path
    save_export(run_state.model_of(run_state.load(str(path / "state.pt"))), str(out))
    return out


def train(spec: dict, state_path: Path, files: list, val: Path, out: Path, minutes: float, part: dict,
          stage: int) -> None:  # fmt: skip
    command = [
        sys.executable, "-m", "gomatch_train.train", "--train", *files, "--val", val, "--out", out,
        "--feature-dim", str(spec["width"]), "--encoder-blocks", str(spec["encoder_blocks"]),
        "--classifier-blocks", str(spec["classifier_blocks"]), "--heads", str(spec.get("heads", 4)),
        "--sinkhorn-iters", str(spec.get("sinkhorn_iters", 20)), "--lr", str(spec["lr"]), "--batch", str(spec["batch"]),
        "--max-points", str(part["max_points"]), "--epochs", "1000", "--max-minutes", str(minutes), "--ckpt-minutes", "10",
        "--log-every", "50", "--seed", str(stage), "--workers", "2", "--threads", "1", "--compile",
        *spec.get("trainer_options", []),
    ]  # fmt: skip
    if spec.get("teacher"):
        teacher = export_of(spec["teacher"], out.parent / "teacher.safetensors")
        command += ["--teacher", teacher, "--distill-weight", str(spec.get("distill_weight", 1.0))]
    if "outlier_rate" in part:
        command += ["--outlier-rate", *(str(r) for r in part["outlier_rate"])]
    if os.environ.get("DEVICE", "cpu") == "cuda":
        command = [c for c in command if c not in ("--compile",)]
        command[command.index("--workers") : command.index("--workers") + 4] = ["--device", "cuda", "--batched"]
    if state_path.exists():
        command += ["--continue", state_path]
    elif spec.get("init"):
        command += ["--init", export_of(spec["init"], out.parent / "init.safetensors")]
    run_command(command, out.parent / "train.log", cwd=HERE)


def evaluate(work: Path, export: Path, val: Path, points: int) -> dict:
    """int8 blob of the export; eval_all.sh at N = 1024 and 256; the trainer's validation metrics."""
    blobs = work / "blobs"
    blobs.mkdir(exist_ok=True)
    tools = REPO / "target" / "release" / "gomatch-tools"
    run_command([tools, "convert", "--input", export, "--precision", "int8", "--output", blobs / "gomatch-int8.bin"],
                work / "convert.log")  # fmt: skip
    result = {}
    for capacity in (1024, 256):
        reports = work / f"eval-{capacity}"
        env = dict(os.environ, PRECISIONS="int8", CAPACITY=str(capacity))
        run_command(["bash", HERE / "eval_all.sh", blobs, reports], work / f"eval-{capacity}.log", env=env)
        result[capacity] = [json.loads((reports / f"{s.split('/')[1]}-int8.json").read_text()) for s in VALIDATION]
    validated = subprocess.run(
        [sys.executable, "-m", "gomatch_train.validate", export, val, "--max-points", str(points)],
        cwd=HERE, check=True, capture_output=True, text=True,
    )  # fmt: skip
    result["validation"] = json.loads(validated.stdout)
    return result


def auc_cell(reports: list) -> str:
    return "; ".join(f"{r['auc_1px']:.1f}/{r['auc_5px']:.1f}/{r['auc_10px']:.1f}" for r in reports)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="folder name under tools/train/stages")
    p.add_argument("minutes", type=float, help="training wall time of this stage")
    args = p.parse_args(argv)
    folder = HERE / "stages" / args.run
    spec = json.loads((folder / "run.json").read_text())
    state_path, log_path = folder / "state.pt", folder / "log.md"
    counters = run_state.load(state_path)["counters"] if state_path.exists() else {"samples": 0, "cpu_minutes": 0.0}
    stage = counters.get("stages", 0) + 1
    data = REPO.parent / "shared" / "data"
    if not data.is_dir():
        raise SystemExit(f"no training data at {data} (../shared/data beside the checkout)")
    cache = Path(os.environ.get("GOMATCH_STAGE_WORK", Path.home() / ".cache" / "gomatch-stages" / args.run))
    work = cache / f"stage-{stage}"
    work.mkdir(parents=True, exist_ok=True)
    sim = REPO / "target" / "release" / "gomatch-sim"
    part = part_for(spec["schedule"], counters["samples"])
    points = part["max_points"]
    print(f"{args.run}: stage {stage}, {counters['samples']} samples so far, {points} points per set", flush=True)

    files = write_data(sim, data, work, stage, spec, part)
    val = validation_data(sim, data, cache, part)
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.monotonic()
    train(spec, state_path, files, val, work / "train", args.minutes, part, stage)
    wall = time.monotonic() - start
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_minutes = (cpu_after.ru_utime + cpu_after.ru_stime - cpu_before.ru_utime - cpu_before.ru_stime) / 60

    checkpoint = torch.load(work / "train" / "checkpoint.pt", map_location="cpu", weights_only=False)
    stage_samples = checkpoint["samples"]
    counters = {
        "stages": stage,
        "samples": counters["samples"] + stage_samples,
        "cpu_minutes": counters["cpu_minutes"] + cpu_minutes,
    }
    run_state.save(run_state.pack(checkpoint, counters), str(state_path))
    result = evaluate(work, work / "train" / "last.safetensors", val, points)
    train_loss = checkpoint["train_totals"].get("loss", float("nan"))
    v = result["validation"]
    row = (
        f"| {stage} | {counters['samples']:,} | {counters['cpu_minutes']:.0f} | "
        f"{budget_cell(part)} | {wall / 60:.0f} | {stage_samples / wall:.1f} | {train_loss:.3f} | "
        f"{v['match_precision']:.3f} / {v['match_recall']:.3f} | {auc_cell(result[1024])} | {auc_cell(result[256])} |\n"
    )  # fmt: skip
    if not log_path.exists():
        log_path.write_text(f"# Staged run `{args.run}`\n\n`tools/train/stage.sh {args.run} MINUTES`; "
                            f"definition in `run.json`.\n\n" + LOG_HEADER)  # fmt: skip
    with open(log_path, "a") as f:
        f.write(row)
    print(row, end="")


if __name__ == "__main__":
    main()
