import sys
from pathlib import Path

import numpy as np
import pytest
import torch

TRAIN_DIR = Path(__file__).resolve().parents[1]
REPO_ROOT = TRAIN_DIR.parents[1]
SHARED = REPO_ROOT.parent / "shared"
REFERENCE = SHARED / "reference"
FIXTURES = REFERENCE / "fixtures"

sys.path.insert(0, str(TRAIN_DIR))


def require(path: Path) -> Path:
    """Skip the calling test with a clear message when shared reference data is absent."""
    if not path.exists():
        pytest.skip(f"shared reference data not found at {path} (expected <repo>/../shared); skipping")
    return path


@pytest.fixture(autouse=True)
def single_thread():
    """The reference fixtures were produced with one thread; tests also stay off the other core."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def data(tmp_path_factory):
    """A tiny synthetic training file (6 samples) and validation file (2 samples)."""
    from gomatch_train.synthetic import random_sample, write_dataset

    root = tmp_path_factory.mktemp("data")
    rng = np.random.default_rng(11)
    write_dataset(str(root / "train.safetensors"), [random_sample(rng, 120, 80, 40) for _ in range(6)])
    write_dataset(str(root / "val.safetensors"), [random_sample(rng, 120, 80, 40) for _ in range(2)])
    return root
