"""Per-point building blocks shared by every stage.

Features are point-major, shape (N, C) for one set or (B, N, C) for a batch of equal-size sets: one row per
keypoint. The reference stores its 1x1 convolutions with
weights of shape (out, in, 1) or (out, in, 1, 1); `PointLinear` keeps exactly that parameter shape so the
state_dict names and shapes equal the reference checkpoint's, and applies it as a per-point linear map.
"""

import math

import torch
import torch.nn.functional as F
from torch import nn

from .compiled import compilable

INSTANCE_NORM_EPS = 1e-5


class PointLinear(nn.Module):
    """A 1x1 convolution applied to point-major features: (N, in) -> (N, out).

    `kernel_dims` is the number of trailing unit dimensions of the stored weight (1 for Conv1d, 2 for Conv2d).
    Initialisation follows PyTorch's default for convolutions (Kaiming-uniform, a = sqrt(5)).
    """

    def __init__(self, in_features: int, out_features: int, bias: bool = True, kernel_dims: int = 1):
        super().__init__()
        self.in_features = in_features
        self.out_features = out_features
        self.weight = nn.Parameter(torch.empty((out_features, in_features) + (1,) * kernel_dims))
        self.bias = nn.Parameter(torch.empty(out_features)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        if self.bias is not None:
            bound = 1.0 / math.sqrt(self.in_features)
            nn.init.uniform_(self.bias, -bound, bound)

    def matrix(self) -> torch.Tensor:
        """The weight as an (out, in) matrix."""
        return self.weight.view(self.out_features, self.in_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, self.matrix(), self.bias)


def instance_norm(x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """InstanceNorm without affine parameters over the rows of a point-major (N, C) or (B, N, C) tensor.

    Per channel: (x - mean) / sqrt(biased_var + 1e-5), statistics over the N rows (one set of points). Without
    gradients it runs on the channel-major view, as the reference's InstanceNorm1d does, so that the rounding is
    the reference's too (the batch-norm kernel on the point-major layout takes another path, a few ulps away);
    with gradients, `PointMajorInstanceNorm` (same function, no layout copies, a cheaper backward). With `valid`
    (B, N) the sets are padded: statistics run over each set's valid rows (`masked_instance_norm`).
    """
    if valid is not None:
        return masked_instance_norm(x, valid)
    if torch.is_grad_enabled():
        return PointMajorInstanceNorm.apply(x)
    batch = x if x.dim() == 3 else x.unsqueeze(0)
    normed = F.instance_norm(batch.transpose(1, 2), eps=INSTANCE_NORM_EPS).transpose(1, 2)
    return normed if x.dim() == 3 else normed.squeeze(0)


def masked_instance_norm(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """`instance_norm` of (B, N, C) padded sets, statistics over the rows where `valid` (B, N) is true; a set of
    one row normalises to zero, as the reference's duplicated single row does. Padding rows stay finite. Statistics
    in float32 or wider (a bf16 input is cast here)."""
    x = at_least_float32(x)
    weight = valid.unsqueeze(-1).to(x.dtype)
    count = weight.sum(dim=-2, keepdim=True).clamp_min(1.0)
    mean = (x * weight).sum(dim=-2, keepdim=True) / count
    centred = x - mean
    variance = (centred.square() * weight).sum(dim=-2, keepdim=True) / count
    return centred * torch.rsqrt(variance + INSTANCE_NORM_EPS)


def at_least_float32(x: torch.Tensor) -> torch.Tensor:
    """x in float32 when it is narrower (a bf16 autocast product): normalisation statistics in full precision."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


class PointMajorInstanceNorm(torch.autograd.Function):
    """`instance_norm` of a point-major (N, C) or (B, N, C) tensor in place of its layout, for training.

    Saves only the output y and 1/sigma: the input gradient is (g - mean(g) - y mean(g y)) / sigma per channel,
    the standard normalisation backward, in five passes over (N, C) instead of the batch-norm kernel's copies.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        y, inv_std = point_major_norm(x)
        ctx.save_for_backward(y, inv_std)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return point_major_norm_backward(grad, *ctx.saved_tensors)


@compilable
def point_major_norm(x: torch.Tensor):
    """(normalised x, 1/sigma) over the rows of each set, float32 or wider (a bf16 input is cast here)."""
    x = at_least_float32(x)
    centred = x - x.mean(dim=-2, keepdim=True)
    inv_std = torch.rsqrt(centred.square().mean(dim=-2, keepdim=True) + INSTANCE_NORM_EPS)
    return centred * inv_std, inv_std


@compilable
def point_major_norm_backward(grad: torch.Tensor, y: torch.Tensor, inv_std: torch.Tensor) -> torch.Tensor:
    mean_grad = grad.mean(dim=-2, keepdim=True)
    mean_grad_y = (grad * y).mean(dim=-2, keepdim=True)
    return (grad - mean_grad - y * mean_grad_y) * inv_std


def on_both_sets(fn, a: torch.Tensor, b: torch.Tensor, *more):
    """(fn(a, *more_a), fn(b, *more_b)) for the two sets of a sample, each argument given as (for a, for b).

    In training, sets of equal shape go through one call stacked along the batch (half the kernel launches, larger
    matrix products; the functions are per set, so the result is the same); inference keeps two calls, whose
    rounding the reference fixtures pin.
    """
    if torch.is_grad_enabled() and a.shape == b.shape and all(x.shape == y.shape for x, y in more):
        both = fn(torch.cat([a, b]), *(torch.cat([x, y]) for x, y in more))
        return both[: len(a)], both[len(a) :]
    return fn(a, *(x for x, _ in more)), fn(b, *(y for _, y in more))


class InstanceNorm(nn.Module):
    """Module form of `instance_norm` (parameter-free), used inside `nn.Sequential` stacks."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return instance_norm(x)
