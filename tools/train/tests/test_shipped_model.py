"""models/: the shipped files match the recorded hashes, and the checkpoint is the paper's configuration."""

import hashlib

from conftest import REPO_ROOT

from gomatch_train.config import ModelConfig
from gomatch_train.export import load_export

MODELS = REPO_ROOT / "models"
SHIPPED_FILES = ["gomatch.safetensors", "gomatch-f32.bin", "gomatch-f16.bin", "gomatch-int8.bin"]


def test_shipped_files_match_the_recorded_hashes():
    recorded = dict(line.split()[::-1] for line in (MODELS / "SHA256SUMS").read_text().splitlines())
    assert sorted(recorded) == sorted(SHIPPED_FILES)
    for name in SHIPPED_FILES:
        assert hashlib.sha256((MODELS / name).read_bytes()).hexdigest() == recorded[name], name


def test_shipped_checkpoint_is_a_paper_configuration_export():
    model = load_export(str(MODELS / "gomatch.safetensors"))
    assert model.config == ModelConfig()  # the paper's: 128 wide, 12 encoder and 4 classifier blocks
    assert sum(p.numel() for p in model.parameters()) == 1_318_402
