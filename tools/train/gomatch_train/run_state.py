"""The committed state of a staged training run (`stage.sh`): weights and Adam state in under 6.1 bytes a
parameter, so that a stage adds at most ~8 MB to the repository for the paper's configuration.

    weights            float32, exact
    Adam first moment  int8 per block of 256 values, scaled by the block's largest magnitude
    Adam second moment its square root, as an 8-bit code of log2 per block (0 = exactly zero): a relative error
                       of at most half a code step (block range / 254 octaves), like 8-bit Adam's dynamic codes;
                       the update m / (sqrt(v) + eps) sees the same relative error
    counters           Adam's step per tensor, the run's steps, samples, CPU minutes, stages

`pack(checkpoint.pt)` reads a trainer checkpoint (train.py), `unpack` gives the model and optimizer state dicts
back (the trainer's `--continue STATE`).
"""

import os

import torch

from .config import ModelConfig
from .model import GoMatch

BLOCK = 256
FORMAT = "gomatch-run-state/1"


def blocks(x: torch.Tensor) -> torch.Tensor:
    """x flattened and zero-padded to whole blocks: (blocks, BLOCK)."""
    flat = x.reshape(-1).float()
    return torch.nn.functional.pad(flat, (0, (-len(flat)) % BLOCK)).view(-1, BLOCK)


def quantize_signed(x: torch.Tensor) -> dict:
    b = blocks(x)
    scale = b.abs().amax(dim=1, keepdim=True).clamp_min(1e-30) / 127
    return {"codes": torch.round(b / scale).to(torch.int8), "scale": scale.squeeze(1), "shape": tuple(x.shape)}


def dequantize_signed(q: dict) -> torch.Tensor:
    values = (q["codes"].float() * q["scale"].unsqueeze(1)).reshape(-1)
    return values[: torch.Size(q["shape"]).numel()].view(q["shape"])


def quantize_log(x: torch.Tensor) -> dict:
    """Non-negative x as codes 1..255 of log2 between the block's smallest and largest positive value, 0 = zero."""
    b = blocks(x)
    positive = b > 0
    log = torch.where(positive, b.clamp_min(1e-45).log2(), torch.zeros_like(b))
    low = torch.where(positive, log, torch.full_like(b, float("inf"))).amin(dim=1, keepdim=True)
    high = torch.where(positive, log, torch.full_like(b, float("-inf"))).amax(dim=1, keepdim=True)
    empty = ~positive.any(dim=1, keepdim=True)
    low, high = torch.where(empty, 0.0, low), torch.where(empty, 0.0, high)
    step = ((high - low) / 254).clamp_min(1e-12)
    codes = torch.where(positive, 1 + torch.round((log - low) / step), torch.zeros_like(b))
    return {"codes": codes.to(torch.uint8), "low": low.squeeze(1), "step": step.squeeze(1), "shape": tuple(x.shape)}


def dequantize_log(q: dict) -> torch.Tensor:
    codes = q["codes"].float()
    values = torch.exp2(q["low"].unsqueeze(1) + (codes - 1) * q["step"].unsqueeze(1))
    values = torch.where(codes > 0, values, torch.zeros_like(values)).reshape(-1)
    return values[: torch.Size(q["shape"]).numel()].view(q["shape"])


def pack(checkpoint: dict, counters: dict) -> dict:
    """The compact state of a trainer checkpoint (`train.py`'s checkpoint.pt contents) and the run's counters."""
    moments = {}
    for index, state in checkpoint["optimizer"]["state"].items():
        moments[index] = {
            "step": float(state["step"]),
            "exp_avg": quantize_signed(state["exp_avg"]),
            "sqrt_exp_avg_sq": quantize_log(state["exp_avg_sq"].sqrt()),
        }
    return {
        "format": FORMAT,
        "config": checkpoint["config"],
        "model": {name: t.float().contiguous() for name, t in checkpoint["model"].items()},
        "moments": moments,
        "param_groups": checkpoint["optimizer"]["param_groups"],
        "counters": counters,
    }


def unpack(state: dict) -> tuple:
    """(model state dict, optimizer state dict, counters) of a packed state."""
    if state.get("format") != FORMAT:
        raise ValueError(f"not a {FORMAT} file (format {state.get('format')!r})")
    optimizer_state = {}
    for index, m in state["moments"].items():
        optimizer_state[index] = {
            "step": torch.tensor(m["step"]),
            "exp_avg": dequantize_signed(m["exp_avg"]),
            "exp_avg_sq": dequantize_log(m["sqrt_exp_avg_sq"]).square(),
        }
    return state["model"], {"state": optimizer_state, "param_groups": state["param_groups"]}, state["counters"]


def config_of(state: dict) -> ModelConfig:
    """The model configuration of a packed state."""
    return ModelConfig.from_json(state["config"])


def model_of(state: dict) -> GoMatch:
    """The model a packed state holds: its configuration with its weights."""
    model = GoMatch(config_of(state))
    model.load_state_dict(state["model"])
    return model


def save(state: dict, path: str) -> None:
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def load(path: str) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)
