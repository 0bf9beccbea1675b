"""models/next: the paper-configuration export that the next GPU session continues (model card, "GPU sessions")."""

import hashlib

from conftest import REPO_ROOT

from gomatch_train.config import ModelConfig
from gomatch_train.export import load_export

NEXT = REPO_ROOT / "models" / "next"


def test_next_model_is_a_paper_configuration_export_with_the_recorded_hash():
    path = NEXT / "gomatch-128-gpu.safetensors"
    recorded = dict(line.split()[::-1] for line in (NEXT / "SHA256SUMS").read_text().splitlines())
    assert hashlib.sha256(path.read_bytes()).hexdigest() == recorded[path.name]
    model = load_export(str(path))
    assert model.config == ModelConfig()  # the paper's: 128 wide, 12 encoder and 4 classifier blocks
    assert sum(p.numel() for p in model.parameters()) == 1_318_402
