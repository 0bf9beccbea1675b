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

from .compiled import compilable
from .layers import INSTANCE_NORM_EPS, InstanceNorm, at_least_float32, on_both_sets, PointLinear, instance_norm

LEAKY_SLOPE = 0.2
# Sets smaller than this attend in float32 under bf16 autocast: PyTorch's CPU flash attention is slower in bf16
# there (N = 256: 1.5 ms more per sample), faster on larger sets (N = 1024).
FLOAT32_ATTENTION_BELOW = 512


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

    W [f_i, f_j - f_i] = (W_c - W_o) f_i + W_o f_j with W = [W_c | W_o]: two per-point products ("centre" and
    "offset" terms) instead of building the (N, K, 2C) edge tensor. LeakyReLU and the normalisation are monotone
    per channel, so both are applied after the max. Without gradients the edges are normalised as the reference
    does (its rounding); with gradients `EdgeMaxNorm` computes the same function from per-point terms.
    """
    xb = x if x.dim() == 3 else x.unsqueeze(0)
    nb = neighbours if neighbours.dim() == 3 else neighbours.unsqueeze(0)
    c = xb.shape[2]
    out = conv.out_features
    w = conv.matrix()
    w_centre, w_offset = w[:, :c], w[:, c:]
    both = xb @ torch.cat([w_centre - w_offset, w_offset], dim=0).t()
    centre, offset = both.split(out, dim=-1)  # (a split's backward is one cat; slices' fill zeros first)
    if torch.is_grad_enabled():
        normed = EdgeMaxNorm.apply(centre, offset, nb)
    else:
        normed = reference_edge_max_norm(centre, offset, nb)
    result = F.leaky_relu(normed, LEAKY_SLOPE)
    return result if x.dim() == 3 else result[0]


def neighbour_rows(offset: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """offset[b, neighbours[b, i, k]] as (B, N, K, C) (one index_select over the flattened batch)."""
    b, n, c = offset.shape
    base = torch.arange(b, device=offset.device).view(b, 1, 1) * n
    return offset.reshape(b * n, c).index_select(0, (neighbours + base).reshape(-1)).view(*neighbours.shape, c)


def reference_edge_max_norm(centre: torch.Tensor, offset: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """max_k IN(centre_i + offset_{n(i,k)}) with the edges materialised and normalised in the reference's order
    (statistics over all K * N edges of a set, channel-major)."""
    b, n, out = centre.shape
    k = neighbours.shape[2]
    gathered = neighbour_rows(offset, neighbours).transpose(1, 2)  # (B, K, N, C), the reference's edge order
    edges = centre.unsqueeze(1) + gathered
    return instance_norm(edges.reshape(b, k * n, out)).view(b, k, n, out).amax(dim=1)


class EdgeMaxNorm(torch.autograd.Function):
    """max_k IN(centre_i + offset_{n(i,k)}) per channel, for training: the statistics over the K * N edges follow
    from per-point sums, and the backward pass needs no (K, N, C) tensor.

    With e_ik = c_i + o_{n(i,k)}, A the neighbour count matrix and d_j the in-degree of point j:
        sum e = K sum c + sum d o,  sum e^2 = K sum c^2 + sum d o^2 + 2 sum c (A o),
        max_k IN(e_ik) = (c_i + max_k o_{n(i,k)} - mean) / sigma     (sigma > 0: the max commutes).
    The backward is the normalisation's (g - mean(g) - y mean(g y)) / sigma restricted to the edges: the upstream
    gradient reaches only each point's maximising edge, so the sums over a point's edges and over the edges
    arriving at a point reduce to A o, A^T c, d and one scatter of g. Both inputs are shifted by their means
    first (the normalisation is invariant to it), which keeps E[e^2] - mean^2 free of cancellation.
    """

    @staticmethod
    def forward(ctx, centre: torch.Tensor, offset: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        saved = edge_max_norm(centre, offset, neighbours)
        ctx.save_for_backward(neighbours, *saved)
        return saved[-1]

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return *edge_max_norm_backward(grad, *ctx.saved_tensors), None


@compilable
def neighbour_maxima(offset: torch.Tensor, neighbours: torch.Tensor):
    """Per point and channel of (B, N, C) `offset`: the maximum over the point's neighbours (B, N, K), the
    neighbour that holds it (the first one on ties) and the sum over them; one gather per neighbour, which
    compiles to a single loop."""
    b, n, c = offset.shape
    rows = offset.reshape(b * n, c)
    base = torch.arange(b, device=offset.device).view(b, 1) * n
    best = argmax_points = total = None
    for j in range(neighbours.shape[2]):
        points = neighbours[:, :, j : j + 1]
        row = rows[(neighbours[:, :, j] + base).reshape(-1)].view(b, n, c)
        if best is None:
            best, argmax_points, total = row, points.expand(b, n, c), row
            continue
        better = row > best
        best = torch.where(better, row, best)
        argmax_points = torch.where(better, points, argmax_points)
        total = total + row
    return best, argmax_points, total


@compilable
def edge_max_norm(centre: torch.Tensor, offset: torch.Tensor, neighbours: torch.Tensor):
    """Forward of `EdgeMaxNorm`: (centre, offset shifted, argmax points, neighbour sums, in-degrees, mean,
    1/sigma, output)."""
    b, n, _ = centre.shape
    k = neighbours.shape[2]
    centre, offset = at_least_float32(centre), at_least_float32(offset)  # (bf16 products: the cast fuses here)
    centre = centre - centre.mean(dim=1, keepdim=True)
    offset = offset - offset.mean(dim=1, keepdim=True)
    maxima, argmax_points, neighbour_sums = neighbour_maxima(offset, neighbours)
    in_degree = torch.zeros(b, n, dtype=centre.dtype, device=centre.device)
    in_degree = in_degree.scatter_add(1, neighbours.reshape(b, n * k), torch.ones_like(in_degree).repeat(1, k))
    in_degree = in_degree.unsqueeze(-1)
    edges = n * k
    mean = (k * centre.sum(dim=1, keepdim=True) + (in_degree * offset).sum(dim=1, keepdim=True)) / edges
    second = (
        k * centre.square().sum(dim=1, keepdim=True)
        + (in_degree * offset.square()).sum(dim=1, keepdim=True)
        + 2 * (centre * neighbour_sums).sum(dim=1, keepdim=True)
    ) / edges
    inv_std = torch.rsqrt((second - mean.square()).clamp_min(0) + INSTANCE_NORM_EPS)
    normed = (centre + maxima - mean) * inv_std
    return centre, offset, argmax_points, neighbour_sums, in_degree, mean, inv_std, normed


@compilable
def edge_max_norm_backward(grad, neighbours, centre, offset, argmax_points, neighbour_sums, in_degree, mean, inv_std,
                           normed):  # fmt: skip
    """Backward of `EdgeMaxNorm`: the gradients of centre and offset."""
    b, n, c = centre.shape
    k = neighbours.shape[2]
    edges = n * k
    mean_grad = grad.sum(dim=1, keepdim=True) / edges
    mean_grad_y = (grad * normed).sum(dim=1, keepdim=True) / edges
    # Sums of y over each point's K edges, and over the edges that arrive at each point.
    y_out = (k * centre + neighbour_sums - k * mean) * inv_std
    base = torch.arange(b, device=centre.device).view(b, 1, 1) * n
    sources = centre.unsqueeze(2).expand(b, n, k, c).reshape(b * n * k, c)
    arriving = torch.zeros_like(centre).reshape(b * n, c).index_add(0, (neighbours + base).reshape(-1), sources)
    y_in = (arriving.view(b, n, c) + in_degree * (offset - mean)) * inv_std
    max_grad = torch.zeros_like(grad).scatter_add(1, argmax_points, grad)
    grad_centre = (grad - k * mean_grad - mean_grad_y * y_out) * inv_std
    grad_offset = (max_grad - in_degree * mean_grad - mean_grad_y * y_in) * inv_std
    return grad_centre, grad_offset


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
        if desc2d.dim() == 2:
            return self.update(desc2d, neighbours2d), self.update(desc3d, neighbours3d)
        return on_both_sets(self.update, desc2d, desc3d, (neighbours2d, neighbours3d))


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

    def head_major(self) -> torch.Tensor:
        """Channel order that puts each head's channels side by side: new channel h * head_dim + p is channel
        p * heads + h."""
        channels = torch.arange(self.heads * self.head_dim, device=self.merge.weight.device)
        return channels.view(self.head_dim, self.heads).t().reshape(-1)

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled():
            return self.fused_forward(x, source)
        q = self.split_heads(self.proj[0](x))
        k = self.split_heads(self.proj[1](source))
        v = self.split_heads(self.proj[2](source))
        scores = torch.matmul(q, k.transpose(-1, -2)) / self.head_dim**0.5
        message = torch.matmul(torch.softmax(scores, dim=-1), v)
        return self.merge(message.movedim(-3, -1).reshape(x.shape))

    def fused_forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        """The same function for training: projections with their output rows in head-major order (so each head's
        query, key and value are contiguous), PyTorch's fused scaled dot-product attention (no N x N scores kept
        for the backward pass), and the merge layer's input columns in the same order."""
        order = self.head_major()

        def heads(layer: PointLinear, features: torch.Tensor) -> torch.Tensor:
            projected = F.linear(features, layer.matrix()[order], layer.bias[order])
            return projected.unflatten(-1, (self.heads, self.head_dim)).transpose(-3, -2)

        q, k, v = heads(self.proj[0], x), heads(self.proj[1], source), heads(self.proj[2], source)
        if source.shape[-2] < FLOAT32_ATTENTION_BELOW:  # in float32 even under bf16 autocast: faster on the CPU
            with torch.autocast(x.device.type, enabled=False):
                message = F.scaled_dot_product_attention(*(at_least_float32(t) for t in (q, k, v)))
        else:
            message = F.scaled_dot_product_attention(q, k, v)
        message = message.transpose(-3, -2).flatten(-2)
        return F.linear(message, self.merge.matrix()[:, order], self.merge.bias)


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

    @compilable
    def forward(self, desc2d, desc3d, neighbours2d, neighbours3d):
        return self.att(desc2d, desc3d, neighbours2d, neighbours3d)
