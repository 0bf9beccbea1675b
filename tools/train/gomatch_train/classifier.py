"""Outlier rejection (paper supp. "Outlier Rejection"): a PointResNet over the set of proposed matches.

Input per match: concat(2D feature, 3D feature) of the L2-normalised descriptors; output one logit per match,
probability = sigmoid(logit). InstanceNorm statistics run over the set of matches, so a single match is
duplicated (a set of one has zero variance).
"""

import torch
from torch import nn

from .encoder import PointResNet
from .layers import PointLinear


class MatchClassifier(nn.Module):
    def __init__(self, feature_dim: int, blocks: int):
        super().__init__()
        self.encoder = PointResNet(2 * feature_dim, feature_dim, blocks)
        self.conv_out = PointLinear(feature_dim, 1)

    def forward(self, desc2d: torch.Tensor, desc3d: torch.Tensor, i2d: torch.Tensor, i3d: torch.Tensor):
        """Logits (M,) for the M matches (i3d[m], i2d[m])."""
        count = i3d.numel()
        if count == 1:
            i3d, i2d = i3d.expand(2), i2d.expand(2)
        features = torch.cat([desc2d[i2d], desc3d[i3d]], dim=1)
        return self.conv_out(self.encoder(features)).squeeze(1)[:count]

    def forward_batch(self, desc2d, desc3d, i2d: torch.Tensor, i3d: torch.Tensor, valid: torch.Tensor):
        """Logits (B, M) for a batch: desc (B, N, C), matches (B, M) padded where `valid` (B, M) is false."""
        sample = torch.arange(len(i2d), device=i2d.device).unsqueeze(1)
        features = torch.cat([desc2d[sample, i2d], desc3d[sample, i3d]], dim=-1)
        return self.conv_out(self.encoder(features, valid)).squeeze(-1)
