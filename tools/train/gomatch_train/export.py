"""The exported checkpoint: what the Rust converter reads.

A float32 safetensors file whose tensor names and shapes are the reference state_dict's (both copies of the shared
encoder, `kp2d_enc.*` and `kp3d_enc.*`, are stored), plus `__metadata__["gomatch_config"]` = ModelConfig as JSON.
"""

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from .config import ModelConfig
from .model import GoMatch

CONFIG_KEY = "gomatch_config"
ENCODER_2D = "matcher.raw_matcher.kp2d_enc."
ENCODER_3D = "matcher.raw_matcher.kp3d_enc."


def export_tensors(model: GoMatch) -> dict:
    """Name -> float32 CPU tensor for every state_dict entry; each entry owns its storage."""
    return {name: t.detach().to("cpu", torch.float32).contiguous().clone() for name, t in model.state_dict().items()}


def save_export(model: GoMatch, path: str) -> None:
    save_file(export_tensors(model), path, metadata={CONFIG_KEY: model.config.to_json()})


def read_config(path: str, default: ModelConfig = ModelConfig()) -> ModelConfig:
    """The file's gomatch_config, or `default` for files without one (e.g. the reference fixture weights)."""
    with safe_open(path, "pt") as f:
        metadata = f.metadata() or {}
    return ModelConfig.from_json(metadata[CONFIG_KEY]) if CONFIG_KEY in metadata else default


def load_export(path: str, default_config: ModelConfig = ModelConfig()) -> GoMatch:
    """Build a model from an exported (or reference) safetensors file; every name and shape must match."""
    config = read_config(path, default_config)
    with safe_open(path, "pt") as f:
        tensors = {name: f.get_tensor(name) for name in f.keys()}
    for name, tensor in tensors.items():
        if name.startswith(ENCODER_3D):
            twin = ENCODER_2D + name[len(ENCODER_3D) :]
            if twin not in tensors or not torch.equal(tensors[twin], tensor):
                raise ValueError(f"shared encoder tensor {name} differs from (or lacks) its 2D copy {twin}")
    model = GoMatch(config)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise ValueError(f"{path}: missing tensors {missing[:5]}, unexpected tensors {unexpected[:5]}")
    for name, tensor in tensors.items():
        if tuple(tensor.shape) != tuple(expected[name].shape):
            raise ValueError(f"{path}: {name} has shape {tuple(tensor.shape)}, expected {tuple(expected[name].shape)}")
    model.load_state_dict(tensors)
    return model
