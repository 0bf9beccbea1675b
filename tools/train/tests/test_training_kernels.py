"""The training step's own kernels compute the reference functions and their exact gradients (float64).

With gradients on, the trainer runs other arithmetic than inference (which the fixture tests pin to the
reference's rounding): point-major InstanceNorm, EdgeConv maxima from per-point sums, fused multi-head attention,
folded residual blocks and the Sinkhorn plan differentiated from its scaling vectors. Each is compared here with
plain autograd through the reference formulation, values and gradients.
"""

import numpy as np
import pytest
import torch

from gomatch_train import compiled
from gomatch_train.attention import FLOAT32_ATTENTION_BELOW, EdgeMaxNorm, MultiHeadAttention, coordinate_neighbours
from gomatch_train.config import ModelConfig
from gomatch_train.encoder import PointResNet, ResidualBlock, matrices_per_step
from gomatch_train.evaluate import assess
from gomatch_train.layers import PointMajorInstanceNorm
from gomatch_train.model import GoMatch
from gomatch_train.sinkhorn import (
    SINKHORN_STOP_THRESHOLD,
    cost_with_dustbins,
    marginals,
    matvec,
    scaling_sinkhorn,
)
from gomatch_train.synthetic import random_sample

F64 = torch.float64


def gradients(fn, inputs, upstream):
    """Values of fn(*inputs) and the gradients of sum(upstream * fn) with respect to every input."""
    inputs = [x.detach().clone().requires_grad_() for x in inputs]
    out = fn(*inputs)
    (out * upstream).sum().backward()
    return out.detach(), [x.grad for x in inputs]


def test_point_major_instance_norm_gradient():
    x = torch.randn(2, 40, 5, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(PointMajorInstanceNorm.apply, (x,))


def materialised_edge_max_norm(centre, offset, neighbours):
    """max_k IN(centre_i + offset_{n(i,k)}) with the (B, N, K, C) edges built, for plain autograd."""
    b, n, c = centre.shape
    k = neighbours.shape[2]
    rows = offset.reshape(b * n, c)[(neighbours + torch.arange(b).view(b, 1, 1) * n).reshape(-1)]
    edges = (centre.unsqueeze(2) + rows.view(b, n, k, c)).reshape(b, n * k, c)
    mean = edges.mean(dim=1, keepdim=True)
    normed = (edges - mean) / torch.sqrt(((edges - mean) ** 2).mean(dim=1, keepdim=True) + 1e-5)
    return normed.view(b, n, k, c).amax(dim=2)


@pytest.mark.parametrize("points,k", [(50, 10), (12, 10), (3, 2)])
def test_edge_max_norm_equals_the_materialised_edges(points, k):
    torch.manual_seed(points)
    neighbours = coordinate_neighbours(torch.rand(2, points, 2, dtype=F64), k)
    centre = torch.randn(2, points, 6, dtype=F64) * 3 + 1  # means far from zero: the shift must hold
    offset = torch.randn(2, points, 6, dtype=F64) * 2 - 4
    upstream = torch.randn(2, points, 6, dtype=F64)
    expected, expected_grads = gradients(
        lambda c, o: materialised_edge_max_norm(c, o, neighbours), (centre, offset), upstream
    )
    got, got_grads = gradients(lambda c, o: EdgeMaxNorm.apply(c, o, neighbours), (centre, offset), upstream)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-12)
    for g, e in zip(got_grads, expected_grads):
        torch.testing.assert_close(g, e, rtol=0, atol=1e-12)


def test_fused_attention_equals_the_reference_heads():
    torch.manual_seed(0)
    attention = MultiHeadAttention(16, 4).double()
    for p in attention.parameters():
        torch.nn.init.normal_(p)
    x, source = torch.randn(2, 30, 16, dtype=F64), torch.randn(2, 25, 16, dtype=F64)
    upstream = torch.randn(2, 30, 16, dtype=F64)
    with torch.no_grad():
        reference = attention(x, source)
    fused, (x_grad,) = gradients(lambda v: attention.fused_forward(v, source), (x,), upstream)
    torch.testing.assert_close(fused, reference, rtol=0, atol=1e-12)
    split = attention.split_heads
    plain, (plain_grad,) = gradients(
        lambda v: attention.merge(
            torch.softmax(split(attention.proj[0](v)) @ split(attention.proj[1](source)).transpose(-1, -2) / 2.0, -1)
            .matmul(split(attention.proj[2](source)))
            .movedim(-3, -1)
            .reshape(v.shape)
        ),
        (x,),
        upstream,
    )
    torch.testing.assert_close(plain, reference, rtol=0, atol=1e-12)
    torch.testing.assert_close(x_grad, plain_grad, rtol=0, atol=1e-10)


def test_folded_residual_block_equals_the_three_layers():
    torch.manual_seed(0)
    block = ResidualBlock(8).double()
    x = torch.randn(2, 20, 8, dtype=F64)
    with torch.no_grad():
        reference = block(x)
    folded = block.folded_forward(x, None, block.folded_matrices())
    torch.testing.assert_close(folded, reference, rtol=0, atol=1e-12)
    folded.sum().backward()
    assert block.preconv[0].weight.grad is not None and block.preconv[0].bias.grad is None


def test_matrices_folded_once_per_step_give_the_per_pass_gradients():
    torch.manual_seed(0)
    encoder = PointResNet(2, 8, 3).double()
    inputs = [torch.randn(2, 20, 2, dtype=F64), torch.randn(1, 15, 2, dtype=F64)]
    upstream = [torch.randn(2, 20, 8, dtype=F64), torch.randn(1, 15, 8, dtype=F64)]

    def per_sample_backward():
        outputs = []
        for x, u in zip(inputs, upstream):
            out = encoder(x)
            (out * u).sum().backward()
            outputs.append(out.detach())
        return outputs

    def gradients():
        return {name: p.grad.clone() for name, p in encoder.named_parameters() if p.grad is not None}

    expected_outputs = per_sample_backward()
    expected = gradients()
    encoder.zero_grad(set_to_none=True)
    with matrices_per_step(encoder):
        assert all(m.is_leaf for pair in encoder.step_matrices for m in pair)
        outputs = per_sample_backward()
        assert set(gradients()) == {"conv_in.0.weight", "conv_in.0.bias"}  # the blocks' stop at the matrices
    assert encoder.step_matrices is None
    got = gradients()
    assert got.keys() == expected.keys() and "conv_0.preconv.0.weight" in got
    for name in expected:
        torch.testing.assert_close(got[name], expected[name], rtol=0, atol=1e-12)
    for out, ref in zip(outputs, expected_outputs):
        torch.testing.assert_close(out, ref, rtol=0, atol=0)


@pytest.mark.parametrize("points", [30, FLOAT32_ATTENTION_BELOW])
def test_bf16_autocast_attention_stays_close_to_float32(points):
    torch.manual_seed(1)
    attention = MultiHeadAttention(32, 4)
    x, source = torch.randn(1, points, 32), torch.randn(1, points, 32)
    expected = attention.fused_forward(x, source)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = attention.fused_forward(x, source)
    torch.testing.assert_close(got.float(), expected, rtol=0, atol=0.05)


def unrolled_scaling_sinkhorn(cost, mu, nu, eps, max_iters):
    """The scaling iteration under plain autograd (every iteration's matrix products recorded)."""
    shift = cost.detach().amin(dim=(-2, -1), keepdim=True)
    log_k = (cost - shift) / -eps
    k = log_k.exp()
    row_mass, col_mass = mu + 1e-8, nu + 1e-8
    b = nu.new_ones(cost.shape[:-2] + nu.shape[-1:])
    log_a_prev = (shift.squeeze(-1) / -eps).expand(cost.shape[:-2] + mu.shape[-1:])
    for _ in range(max_iters):
        a = row_mass / matvec(k, b)
        b = col_mass / matvec(k.transpose(-2, -1), a)
        log_a = a.log()
        if (eps * (log_a - log_a_prev)).norm(dim=-1).max() < SINKHORN_STOP_THRESHOLD:
            break
        log_a_prev = log_a
    return log_a.unsqueeze(-1) + log_k + b.log().unsqueeze(-2)


@pytest.mark.parametrize("batch,n3d,n2d,iterations", [(1, 30, 40, 20), (3, 25, 20, 20), (2, 10, 12, 3), (1, 5, 5, 60)])
def test_sinkhorn_plan_gradient_equals_the_unrolled_iteration(batch, n3d, n2d, iterations):
    torch.manual_seed(n3d)
    distances = torch.rand(batch, n3d, n2d, dtype=F64) * 2
    bin_score = torch.tensor(1.0, dtype=F64)
    upstream = torch.randn(batch, n3d + 1, n2d + 1, dtype=F64)

    def plan(solver):
        def run(d, s):
            cost = cost_with_dustbins(d, s)
            mu, nu = marginals(n3d, n2d, cost)
            result = solver(cost, mu, nu, 0.1, iterations)
            return result[0] if isinstance(result, tuple) else result

        return run

    expected, expected_grads = gradients(plan(unrolled_scaling_sinkhorn), (distances, bin_score), upstream)
    got, got_grads = gradients(plan(scaling_sinkhorn), (distances, bin_score), upstream)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-12)
    for g, e in zip(got_grads, expected_grads):
        torch.testing.assert_close(g, e, rtol=1e-10, atol=1e-10)


def test_compiled_training_step_agrees_with_eager():
    """`--compile`: the compiled functions give the eager loss and gradients up to float32 rounding."""
    torch.manual_seed(0)
    pts2d, pts3d, match = (torch.from_numpy(a) for a in random_sample(np.random.default_rng(2), 150, 90, 50))
    model = GoMatch(ModelConfig(feature_dim=32, encoder_blocks=2, classifier_blocks=1))

    def step():
        model.zero_grad()
        loss = assess(model(pts2d, pts3d), match, 0.5).loss
        loss.backward()
        return loss.item(), [None if p.grad is None else p.grad.clone() for p in model.parameters()]

    eager_loss, eager_grads = step()
    compiled.enable()
    try:
        compiled_loss, compiled_grads = step()
    finally:
        compiled.disable()
    assert abs(compiled_loss - eager_loss) < 1e-4 * abs(eager_loss)
    scale = max(e.abs().max().item() for e in eager_grads if e is not None)
    for c, e in zip(compiled_grads, eager_grads):
        assert (c is None) == (e is None)
        if e is not None:  # some gradients are zero up to rounding (a bias cancelled further on): absolute scale
            torch.testing.assert_close(c, e, rtol=1e-3, atol=1e-3 * scale)
