"""The exported checkpoint format: names and shapes of the reference state_dict, float32, config metadata."""

import json
import re

import numpy as np
import pytest
import torch
from conftest import REFERENCE, require
from safetensors import safe_open
from safetensors.torch import save_file

from gomatch_train.config import ModelConfig
from gomatch_train.export import export_tensors, load_export, save_export
from gomatch_train.model import GoMatch

CONFIG_KEYS = {
    "feature_dim", "encoder_blocks", "classifier_blocks", "heads", "knn", "sinkhorn_iters", "sinkhorn_eps",
    "match_threshold",
}  # fmt: skip


def reference_params() -> dict:
    """name -> shape tuple from params.tsv ("scalar" is a 0-d tensor)."""
    params = {}
    for line in require(REFERENCE / "params.tsv").read_text().splitlines()[1:]:
        if not line or line.startswith("#") or line.startswith("TOTAL"):
            continue
        name, shape, dtype, _ = line.split("\t")
        assert dtype == "float32"
        params[name] = () if shape == "scalar" else tuple(int(v) for v in shape.split("x"))
    return params


def shapes(model: GoMatch) -> dict:
    return {name: tuple(t.shape) for name, t in model.state_dict().items()}


def test_default_model_has_the_reference_parameter_names_and_shapes():
    reference = reference_params()
    model = GoMatch(ModelConfig())
    assert shapes(model) == reference
    # The shared encoder is one module: parameters() counts it once, like the reference's 1,318,402.
    assert sum(p.numel() for p in model.parameters()) == 1_318_402


def test_narrow_model_follows_the_reference_name_pattern():
    reference = reference_params()
    config = ModelConfig(feature_dim=64, encoder_blocks=4, classifier_blocks=2)

    def kept(name):
        block = re.search(r"(kp[23]d_enc|classifier\.encoder)\.conv_(\d+)\.", name)
        if block is None:
            return True
        limit = config.classifier_blocks if block.group(1) == "classifier.encoder" else config.encoder_blocks
        return int(block.group(2)) < limit

    halve = {128: 64, 256: 128, 512: 256}
    expected = {n: tuple(halve.get(d, d) for d in s) for n, s in reference.items() if kept(n)}
    assert shapes(GoMatch(config)) == expected


def test_export_round_trip(tmp_path):
    torch.manual_seed(3)
    config = ModelConfig(feature_dim=32, encoder_blocks=3, classifier_blocks=2)
    model = GoMatch(config).eval()
    path = tmp_path / "model.safetensors"
    save_export(model, str(path))

    with safe_open(str(path), "pt") as f:
        names = set(f.keys())
        metadata = f.metadata()
        stored = {n: f.get_tensor(n) for n in names}
    assert names == set(model.state_dict())
    assert all(t.dtype == torch.float32 for t in stored.values())
    enc2d = {n[len("matcher.raw_matcher.kp2d_enc.") :] for n in names if ".kp2d_enc." in n}
    enc3d = {n[len("matcher.raw_matcher.kp3d_enc.") :] for n in names if ".kp3d_enc." in n}
    assert enc2d == enc3d and len(enc2d) == 2 + 6 * config.encoder_blocks
    assert stored["matcher.raw_matcher.bin_score"].shape == ()

    saved_config = json.loads(metadata["gomatch_config"])
    assert set(saved_config) == CONFIG_KEYS
    assert saved_config["feature_dim"] == 32 and saved_config["match_threshold"] == 0.5

    loaded = load_export(str(path)).eval()
    assert loaded.config == config
    rng = np.random.default_rng(0)
    pts2d = torch.from_numpy(rng.uniform(-0.5, 0.5, (40, 2)).astype(np.float32))
    pts3d = torch.from_numpy(rng.uniform(-0.5, 0.5, (50, 2)).astype(np.float32))
    with torch.no_grad():
        a, b = model(pts2d, pts3d), loaded(pts2d, pts3d)
    assert torch.equal(a.log_plan, b.log_plan) and torch.equal(a.cls_logits, b.cls_logits)


def test_load_rejects_diverging_encoder_copies(tmp_path):
    model = GoMatch(ModelConfig(feature_dim=16, encoder_blocks=1, classifier_blocks=1))
    tensors = export_tensors(model)
    tensors["matcher.raw_matcher.kp3d_enc.conv_in.0.bias"] += 1.0
    path = tmp_path / "bad.safetensors"
    save_file(tensors, str(path), metadata={"gomatch_config": model.config.to_json()})
    with pytest.raises(ValueError, match="kp3d_enc.conv_in.0.bias"):
        load_export(str(path))


def test_load_rejects_wrong_shapes(tmp_path):
    model = GoMatch(ModelConfig(feature_dim=16, encoder_blocks=1, classifier_blocks=1))
    path = tmp_path / "narrow.safetensors"
    save_export(model, str(path))
    with safe_open(str(path), "pt") as f:
        tensors = {n: f.get_tensor(n) for n in f.keys()}
    wrong = ModelConfig(feature_dim=32, encoder_blocks=1, classifier_blocks=1)
    save_file(tensors, str(path), metadata={"gomatch_config": wrong.to_json()})
    with pytest.raises(ValueError, match="shape"):
        load_export(str(path))
