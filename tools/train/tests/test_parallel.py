"""Data-parallel workers: summed gradients equal the single-process gradient; W=2 runs resume exactly."""

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from test_training import cli, exported

from gomatch_train import train
from gomatch_train.config import ModelConfig
from gomatch_train.evaluate import assess
from gomatch_train.model import GoMatch
from gomatch_train.parallel import launch
from gomatch_train.synthetic import random_sample


def batch_gradients(args, group):
    """Mean-loss gradient of a fixed batch of 5 samples, this process computing its share; saved by rank 0."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = GoMatch(ModelConfig(feature_dim=16, encoder_blocks=1, classifier_blocks=1))
    rng = np.random.default_rng(4)
    batch = [[torch.from_numpy(a) for a in random_sample(rng, 80, 50, 20)] for _ in range(5)]
    for pts2d, pts3d, match in group.share(batch):
        (assess(model(pts2d, pts3d), match, 0.5).loss / len(batch)).backward()
    group.sum_gradients(model.parameters())
    if group.is_main:
        # Biases in front of an InstanceNorm get no gradient in training (they cancel); summed over workers: zero.
        torch.save({n: p.grad if p.grad is not None else torch.zeros_like(p) for n, p in model.named_parameters()},
                   args.out)  # fmt: skip


def sleep_in_workers(args, group):
    """Writes this worker's pid, then idles as a long training step would, deaf to SIGINT: torch's spawn asks for
    SIGINT at the parent's death, and workers of a stopped stage were seen training on after it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    Path(args.out, f"{group.rank}.pid").write_text(str(os.getpid()))
    time.sleep(120)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie is ended; only its parent (gone here) could reap it.
    status = Path(f"/proc/{pid}/status")
    return not (status.exists() and "zombie" in status.read_text())


def test_workers_end_with_the_process_that_launched_them(tmp_path):
    here = Path(__file__).resolve().parent
    script = (
        f"import sys, argparse; sys.path[:0] = [{str(here)!r}, {str(here.parent)!r}]\n"
        "from gomatch_train.parallel import launch\nfrom test_parallel import sleep_in_workers\n"
        f"launch(sleep_in_workers, argparse.Namespace(out={str(tmp_path)!r}), 2)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script])
    pid_files = [tmp_path / "0.pid", tmp_path / "1.pid"]
    deadline = time.monotonic() + 60
    while not all(f.exists() and f.read_text() for f in pid_files) and time.monotonic() < deadline:
        time.sleep(0.1)
    workers = [int(f.read_text()) for f in pid_files]
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 20
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(w) for w in workers), "workers outlived their parent"


def test_two_workers_sum_to_the_single_process_gradient(tmp_path):
    one, two = tmp_path / "one.pt", tmp_path / "two.pt"
    launch(batch_gradients, argparse.Namespace(out=str(one)), 1)
    launch(batch_gradients, argparse.Namespace(out=str(two)), 2)
    a, b = torch.load(one), torch.load(two)
    assert a.keys() == b.keys()
    for name in a:
        scale = a[name].abs().max().item()
        assert torch.allclose(a[name], b[name], atol=1e-5 * max(scale, 1e-6)), name


def test_two_workers_resume_exactly(data, tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train.main(cli(data, straight, "--epochs", "1", "--workers", "2"))
    train.main(cli(data, resumed, "--epochs", "1", "--workers", "2", "--max-steps", "1"))
    train.main(cli(data, resumed, "--epochs", "1", "--workers", "2", "--resume"))
    a, b = exported(straight / "last.safetensors"), exported(resumed / "last.safetensors")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert (resumed / "history.jsonl").read_text() == (straight / "history.jsonl").read_text()
