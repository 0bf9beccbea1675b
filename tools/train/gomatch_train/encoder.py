"""Point encoder (paper supp. "Feature Encoder", Fig. "encoder"): PointResNet.

    x = conv_in(points)                       per-point linear in -> width
    for each residual block:
        y = preconv(x)                        linear, no norm, no activation
        y = InstanceNorm(conv1(y))
        y = InstanceNorm(conv2(y))
        x = ReLU(y) + x

The same module (with a different input width) is the trunk of the outlier classifier.
"""

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
        if torch.is_grad_enabled():
            return self.folded_forward(x, valid)
        y = instance_norm(self.conv1(self.preconv(x)), valid)
        y = instance_norm(self.conv2(y), valid)
        return F.relu(y) + x

    def folded_forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """The same function for training, in two products instead of three: preconv and conv1 have no
        nonlinearity between them, so they act as the one matrix W1 W0, and every bias in front of an
        InstanceNorm cancels with the set's mean (their gradients are exactly zero)."""
        first = self.conv1[0].matrix() @ self.preconv[0].matrix()
        y = instance_norm(F.linear(x, first), valid)
        y = instance_norm(F.linear(y, self.conv2[0].matrix()), valid)
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

    @compilable
    def forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """`valid` (B, N): padded sets, InstanceNorm over the valid rows (see `instance_norm`)."""
        x = self.conv_in(x)
        for i in range(self.blocks):
            x = getattr(self, f"conv_{i}")(x, valid)
        return x
