"""Point encoder (paper supp. "Feature Encoder", Fig. "encoder"): PointResNet.

    x = conv_in(points)                       per-point linear in -> width
    for each residual block:
        y = preconv(x)                        linear, no norm, no activation
        y = InstanceNorm(conv1(y))
        y = InstanceNorm(conv2(y))
        x = ReLU(y) + x

The same module (with a different input width) is the trunk of the outlier classifier.
"""

import contextlib

import torch
import torch.nn.functional as F
from torch import nn

from .compiled import compilable
from .layers import PointLinear, instance_norm


class ResidualBlock(nn.Module):
    """One residual block; submodule names mirror the reference (`preconv.0`, `conv1.0`, `conv2.0`)."""

    def __init__(self, width: int):
        super().__init__()
        self.preconv = nn.Sequential(PointLinear(width, width))
        self.conv1 = nn.Sequential(PointLinear(width, width))
        self.conv2 = nn.Sequential(PointLinear(width, width))

    def forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """The reference's three layers (inference; training runs `folded_forward` from `PointResNet`)."""
        y = instance_norm(self.conv1(self.preconv(x)), valid)
        y = instance_norm(self.conv2(y), valid)
        return F.relu(y) + x

    def folded_matrices(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The block's two matrices for training: preconv and conv1 have no nonlinearity between them, so they
        act as the one matrix W1 W0; then W2. Every bias in front of an InstanceNorm cancels with the set's mean
        (their gradients are exactly zero), so none is applied."""
        return self.conv1[0].matrix() @ self.preconv[0].matrix(), self.conv2[0].matrix()

    @staticmethod
    def folded_forward(x, valid, matrices) -> torch.Tensor:
        """The same function for training, in two products instead of three (`folded_matrices`)."""
        first, second = matrices
        y = instance_norm(F.linear(x, first), valid)
        y = instance_norm(F.linear(y, second), valid)
        return F.relu(y) + x


class PointResNet(nn.Module):
    """(N, in_channels) -> (N, width), or batched (B, N, in_channels) -> (B, N, width); InstanceNorm statistics
    run over the N points of each set."""

    def __init__(self, in_channels: int, width: int, blocks: int):
        super().__init__()
        self.conv_in = nn.Sequential(PointLinear(in_channels, width))
        self.blocks = blocks
        for i in range(blocks):
            self.add_module(f"conv_{i}", ResidualBlock(width))
        self.step_matrices = None  # set by `matrices_per_step`

    def residual_blocks(self) -> list:
        return [getattr(self, f"conv_{i}") for i in range(self.blocks)]

    def forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """`valid` (B, N): padded sets, InstanceNorm over the valid rows (see `instance_norm`)."""
        if not torch.is_grad_enabled():
            return self.inference_forward(x, valid)
        matrices = self.step_matrices
        if matrices is None:
            matrices = [block.folded_matrices() for block in self.residual_blocks()]
        return self.training_forward(x, valid, matrices)

    @compilable
    def inference_forward(self, x: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
        x = self.conv_in(x)
        for block in self.residual_blocks():
            x = block(x, valid)
        return x

    @compilable
    def training_forward(self, x: torch.Tensor, valid: torch.Tensor | None, matrices: list) -> torch.Tensor:
        x = self.conv_in(x)
        for block_matrices in matrices:
            x = ResidualBlock.folded_forward(x, valid, block_matrices)
        return x


@contextlib.contextmanager
def matrices_per_step(model: nn.Module):
    """Within the block, every `PointResNet` of `model` trains with its blocks' matrices folded once
    (`ResidualBlock.folded_matrices`) instead of once per forward pass (one optimizer step: many samples). The
    forward passes' backward calls accumulate the gradients of those matrices; on a normal exit they flow on
    to the weights in one backward call: the same gradients, without the folding's three products per sample."""
    encoders = [m for m in model.modules() if isinstance(m, PointResNet)]
    folded = [[block.folded_matrices() for block in encoder.residual_blocks()] for encoder in encoders]
    leaves = [[tuple(m.detach().requires_grad_() for m in pair) for pair in matrices] for matrices in folded]
    for encoder, matrices in zip(encoders, leaves):
        encoder.step_matrices = matrices
    try:
        yield
    finally:
        for encoder in encoders:
            encoder.step_matrices = None
    products = [m for matrices in folded for pair in matrices for m in pair]
    stand_ins = [m for matrices in leaves for pair in matrices for m in pair]
    pairs = [(product, leaf.grad) for product, leaf in zip(products, stand_ins) if leaf.grad is not None]
    if pairs:
        torch.autograd.backward([p for p, _ in pairs], [g for _, g in pairs])
