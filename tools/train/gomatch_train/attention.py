"""Attention module (paper sec. 3, supp. eq. 4-8): layers ("self", "cross", "self"), each shared by both sets.

Self layer: EdgeConv over the k nearest neighbours in COORDINATE space (the bearing coordinates of the set),
    edge(i, j) = concat(f_i, f_j - f_i), InstanceNorm over all (point, neighbour) entries, LeakyReLU(0.2),
    max over neighbours; two such stages, then a per-point layer on concat(x0, x1, x2). Replaces the features.
Cross layer: multi-head attention of one set onto the other (SuperGlue's attentional propagation) with a
    residual update, applied sequentially: desc2d first, then desc3d attends to the UPDATED desc2d.
"""

import torch
import torch.nn.functional as F
from torch import nn

from .layers import InstanceNorm, PointLinear, instance_norm

LEAKY_SLOPE = 0.2


@torch.no_grad()
def coordinate_neighbours(coords: torch.Tensor, k: int) -> torch.Tensor:
    """Indices (N, min(k, N-1)) of each point's nearest neighbours in coordinate space, nearest first; for a batch
    (B, N, 2) of equal-size sets, (B, N, min(k, N-1)).

    Squared distances |a|^2 + |b|^2 - 2ab clamped at 1e-12; the k+1 smallest are taken and the first one (the
    point itself) dropped. The arithmetic order follows the reference so that ties break identically.
    """
    c = coords if coords.dim() == 3 else coords.unsqueeze(0)
    n = c.shape[1]
    if n < 2:
        raise ValueError(f"self attention needs at least 2 points per set, got {n}")
    k = min(k, n - 1)
    sq = torch.sum(c**2, dim=-1)
    dist = -2 * torch.matmul(c, c.transpose(1, 2))
    dist += sq[:, :, None]
    dist += sq[:, None, :]
    dist = torch.clamp(dist, min=1e-12)
    idx = dist.topk(k=k + 1, dim=-1, largest=False, sorted=True)[1][:, :, 1:]
    return idx if coords.dim() == 3 else idx[0]


def edge_conv_max(x: torch.Tensor, neighbours: torch.Tensor, conv: PointLinear) -> torch.Tensor:
    """max_j LeakyReLU(IN(W concat(f_i, f_j - f_i))) over the neighbours j of each point i; x is (N, C) or a batch
    (B, N, C) with neighbours (N, K) or (B, N, K).

    W [f_i, f_j - f_i] = (W_c - W_o) f_i + W_o f_j with W = [W_c | W_o]: two per-point products and a gather of
    (K, N, out) instead of building the (N, K, 2C) edge tensor. LeakyReLU is monotone, so it is applied after
    the max (same result, on N instead of N*K entries).
    """
    xb = x if x.dim() == 3 else x.unsqueeze(0)
    nb = neighbours if neighbours.dim() == 3 else neighbours.unsqueeze(0)
    b, n, c = xb.shape
    k = nb.shape[2]
    out = conv.out_features
    w = conv.matrix()
    w_centre, w_offset = w[:, :c], w[:, c:]
    both = xb @ torch.cat([w_centre - w_offset, w_offset], dim=0).t()
    centre, offset = both[..., :out], both[..., out:]
    sample = torch.arange(b, device=x.device).unsqueeze(1)
    gathered = offset[sample, nb.transpose(1, 2).reshape(b, k * n)]
    edges = centre.unsqueeze(1) + gathered.view(b, k, n, out)
    edges = instance_norm(edges.view(b, k * n, out)).view(b, k, n, out)
    result = F.leaky_relu(edges.amax(dim=1), LEAKY_SLOPE)
    return result if x.dim() == 3 else result[0]


class EdgeConvSelfAttention(nn.Module):
    """Self layer (DGCNN/Predator EdgeConv). Weights (out, in, 1, 1) without bias, as in the reference."""

    def __init__(self, width: int):
        super().__init__()
        self.conv1 = PointLinear(2 * width, width, bias=False, kernel_dims=2)
        self.conv2 = PointLinear(2 * width, 2 * width, bias=False, kernel_dims=2)
        self.conv3 = PointLinear(4 * width, width, bias=False, kernel_dims=2)

    def update(self, x0: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        x1 = edge_conv_max(x0, neighbours, self.conv1)
        x2 = edge_conv_max(x1, neighbours, self.conv2)
        x3 = self.conv3(torch.cat([x0, x1, x2], dim=-1))
        return F.leaky_relu(instance_norm(x3), LEAKY_SLOPE)

    def forward(self, desc2d, desc3d, neighbours2d, neighbours3d):
        return self.update(desc2d, neighbours2d), self.update(desc3d, neighbours3d)


class MultiHeadAttention(nn.Module):
    """Scaled dot-product attention with `heads` heads over per-point projections.

    Head split of a width-C feature: channel c belongs to head c % heads at head position c // heads (the head
    index is the fast axis), and the merged message uses the same interleaved layout.
    """

    def __init__(self, width: int, heads: int):
        super().__init__()
        if width % heads != 0:
            raise ValueError(f"feature width {width} is not divisible by {heads} heads")
        self.heads = heads
        self.head_dim = width // heads
        self.merge = PointLinear(width, width)
        self.proj = nn.ModuleList([PointLinear(width, width) for _ in range(3)])
        for p in self.proj:
            p.load_state_dict(self.merge.state_dict())

    def split_heads(self, x: torch.Tensor) -> torch.Tensor:
        """(..., N, C) -> (..., heads, N, head_dim)."""
        return x.view(*x.shape[:-1], self.head_dim, self.heads).movedim(-1, -3)

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        q = self.split_heads(self.proj[0](x))
        k = self.split_heads(self.proj[1](source))
        v = self.split_heads(self.proj[2](source))
        scores = torch.matmul(q, k.transpose(-1, -2)) / self.head_dim**0.5
        message = torch.matmul(torch.softmax(scores, dim=-1), v)
        return self.merge(message.movedim(-3, -1).reshape(x.shape))


class CrossAttention(nn.Module):
    """Cross layer: delta(x, source) = MLP(concat(x, attention(x, source))), residual, 2D updated first."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.attn = MultiHeadAttention(width, heads)
        self.mlp = nn.Sequential(
            PointLinear(2 * width, 2 * width), InstanceNorm(), nn.ReLU(), PointLinear(2 * width, width)
        )
        nn.init.zeros_(self.mlp[3].bias)

    def delta(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([x, self.attn(x, source)], dim=-1))

    def forward(self, desc2d, desc3d, neighbours2d, neighbours3d):
        desc2d = desc2d + self.delta(desc2d, desc3d)
        desc3d = desc3d + self.delta(desc3d, desc2d)
        return desc2d, desc3d


class SelfCrossAttention(nn.Module):
    """The layer stack ("self", "cross", "self"); every layer maps (desc2d, desc3d) -> (desc2d, desc3d)."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.layers = nn.ModuleList(
            [EdgeConvSelfAttention(width), CrossAttention(width, heads), EdgeConvSelfAttention(width)]
        )

    def forward(self, desc2d, desc3d, neighbours2d, neighbours3d):
        for layer in self.layers:
            desc2d, desc3d = layer(desc2d, desc3d, neighbours2d, neighbours3d)
        return desc2d, desc3d


class Attention(nn.Module):
    """Holds the stack as `att` so parameter names read `attention.att.layers.{i}...` like the reference."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.att = SelfCrossAttention(width, heads)

    def forward(self, desc2d, desc3d, neighbours2d, neighbours3d):
        return self.att(desc2d, desc3d, neighbours2d, neighbours3d)
