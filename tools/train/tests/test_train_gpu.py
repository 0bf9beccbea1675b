"""tools/train/train_gpu.sh end to end, on the CPU (DEVICE=cpu) with one synthetic scene per seed, four queries per
real scene and two short runs: a new model and a fine-tuned shipped one. Needs `gomatch-sim` (./test.sh builds it) and ../shared/data."""

import os
import subprocess
import sys

import pytest
from conftest import REPO_ROOT, SHARED, require

from gomatch_train.config import ModelConfig
from gomatch_train.export import load_export

GOMATCH_SIM = REPO_ROOT / "target" / "release" / "gomatch-sim"


def test_gpu_script_writes_data_trains_every_run_and_collects_the_exports(tmp_path):
    data = require(SHARED / "data")
    if not GOMATCH_SIM.exists():
        pytest.skip(f"{GOMATCH_SIM} not built (cargo build --release -p gomatch-sim); skipping")
    env = dict(os.environ, DEVICE="cpu", SYNTHETIC_SCENES="1", REAL_QUERIES="4", PYTHON=sys.executable)
    # At most 128 points per set: one batch of 32 samples of the full model at 1024 takes minutes on a CPU.
    small = "--max-points,128"
    runs = ["tiny::16:1:1:" + small, "shipped:models/gomatch.safetensors:128:12:4:--lr,1e-4,--outlier-rate,0.5,0.9," + small]
    script = REPO_ROOT / "tools" / "train" / "train_gpu.sh"
    done = subprocess.run(
        ["bash", str(script), str(GOMATCH_SIM), str(data), str(tmp_path), "0.02", *runs],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert "data written in" in done.stdout
    for name, config in (("tiny", ModelConfig(16, 1, 1)), ("shipped", ModelConfig())):
        log = (tmp_path / f"{name}.log").read_text()
        assert "% of their points kept by the equal-size crops" in log and "stopping at step" in log, log
        options = "Adam lr 0.0001, batch 32, outlier rate 0.5-0.9" if name == "shipped" else "Adam lr 0.001, batch 32"
        assert options in log, log
        assert load_export(str(tmp_path / f"{name}-last.safetensors")).config == config
