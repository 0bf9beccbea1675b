"""Losses (paper eq. 2, 3) and the mutual assignment on hand-made inputs."""

import math

import torch

from gomatch_train.loss import classifier_labels, classifier_loss, distillation_loss, match_loss
from gomatch_train.sinkhorn import log_sinkhorn, marginals, mutual_assignment, scaling_sinkhorn, transport


def test_match_loss_averages_gt_matches_and_dustbins():
    # 3 3D points (rows) + dustbin, 3 keypoints (columns) + dustbin.
    log_plan = torch.arange(16, dtype=torch.float32).view(4, 4) * -0.1
    match = torch.tensor([2, -1, 0])  # kp0-3D2, kp2-3D0, kp1 unmatched, 3D1 unmatched
    expected = -(log_plan[2, 0] + log_plan[0, 2] + log_plan[3, 1] + log_plan[1, 3]) / 4
    assert torch.allclose(match_loss(log_plan, match), expected)


def test_classifier_loss_balances_positives_and_negatives():
    logits = torch.tensor([2.0, -1.0, 0.5, 0.0])
    labels = torch.tensor([1.0, 0.0, 0.0, 0.0])

    def bce(z, y):
        p = 1 / (1 + math.exp(-z))
        return -(y * math.log(p) + (1 - y) * math.log(1 - p))

    # positive weight = #neg / #pos = 3, negatives weight 1, mean over the 4 matches
    expected = (3 * bce(2.0, 1) + bce(-1.0, 0) + bce(0.5, 0) + bce(0.0, 0)) / 4
    assert abs(classifier_loss(logits, labels).item() - expected) < 1e-6


def test_classifier_loss_is_zero_without_positives_and_keeps_the_graph():
    logits = torch.tensor([0.3, -0.2], requires_grad=True)
    loss = classifier_loss(logits, torch.zeros(2))
    assert loss.item() == 0.0
    loss.backward()
    assert torch.equal(logits.grad, torch.zeros(2))


def test_classifier_labels_compare_with_ground_truth():
    match = torch.tensor([1, -1, 0])
    labels = classifier_labels(torch.tensor([0, 1, 1]), torch.tensor([2, 0, 1]), match)
    assert labels.tolist() == [1.0, 1.0, 0.0]


def plan_with(pairs, n3d, n2d, extra=()):
    plan = torch.full((n3d + 1, n2d + 1), 0.01)
    for r, c in pairs:
        plan[r, c] = 0.5
    for r, c, v in extra:
        plan[r, c] = v
    return plan


def test_mutual_assignment_keeps_only_mutual_pairs_when_more_than_four():
    pairs = [(0, 1), (1, 0), (2, 2), (3, 4), (4, 3)]
    # 3D row 5's best column is 2, but column 2 prefers row 2: one-way only, dropped.
    plan = plan_with(pairs, 6, 5, extra=[(5, 2, 0.3)])
    i3d, i2d = mutual_assignment(plan)
    assert list(zip(i3d.tolist(), i2d.tolist())) == sorted(pairs)


def test_mutual_assignment_falls_back_to_one_way_pairs_when_at_most_four():
    pairs = [(0, 1), (1, 0)]
    plan = plan_with(pairs, 3, 3, extra=[(2, 2, 0.3), (0, 2, 0.4)])
    # row 2 -> col 2 and col 2 -> row 0 are one-way; mutual pairs are (0,1), (1,0): 2 <= 4 -> union.
    i3d, i2d = mutual_assignment(plan)
    assert list(zip(i3d.tolist(), i2d.tolist())) == [(0, 1), (0, 2), (1, 0), (2, 2)]


def test_sinkhorn_plan_has_the_requested_marginals():
    torch.manual_seed(0)
    n3d, n2d = 7, 5
    cost = torch.rand(n3d + 1, n2d + 1)
    mu, nu = marginals(n3d, n2d, cost)
    log_plan, iterations = log_sinkhorn(cost, mu, nu, eps=0.1, max_iters=200)
    plan = log_plan.exp()
    assert iterations < 200  # converged, stopped early
    assert torch.allclose(plan.sum(1), mu, atol=1e-5)
    assert torch.allclose(plan.sum(0), nu, atol=1e-5)


def random_cost(n3d, n2d, seed=0):
    torch.manual_seed(seed)
    cost = torch.rand(n3d + 1, n2d + 1) * 1.5
    cost[-1, :] = 1.0
    cost[:, -1] = 1.0
    return cost


def test_exp_domain_sinkhorn_matches_the_log_domain_iteration_and_gradient():
    n3d, n2d = 60, 45
    cost = random_cost(n3d, n2d).requires_grad_()
    mu, nu = marginals(n3d, n2d, cost)
    reference, iters_ref = log_sinkhorn(cost, mu, nu, 0.1, 20)
    fast, iters_fast = scaling_sinkhorn(cost, mu, nu, 0.1, 20)
    assert iters_fast == iters_ref
    assert torch.allclose(fast, reference, atol=1e-4)
    assert torch.allclose(fast.exp(), reference.exp(), atol=1e-6)

    weights = torch.rand_like(reference)
    (grad_ref,) = torch.autograd.grad((reference * weights).sum(), cost)
    (grad_fast,) = torch.autograd.grad((fast * weights).sum(), cost)
    assert torch.allclose(grad_fast, grad_ref, atol=1e-3 * grad_ref.abs().max().item())


def test_transport_uses_the_reference_arithmetic_without_autograd_and_for_wide_cost_ranges():
    n3d, n2d = 30, 20
    cost = random_cost(n3d, n2d, seed=1)
    mu, nu = marginals(n3d, n2d, cost)
    with torch.no_grad():
        assert torch.equal(transport(cost, mu, nu, 0.1, 20)[0], log_sinkhorn(cost, mu, nu, 0.1, 20)[0])
    wide = cost.clone()
    wide[-1, -1] = 9.0  # (max - min) / eps > 80: exp(-cost / eps) would underflow
    assert torch.equal(transport(wide, mu, nu, 0.1, 20)[0], log_sinkhorn(wide, mu, nu, 0.1, 20)[0])
    assert not torch.equal(transport(cost, mu, nu, 0.1, 20)[0], log_sinkhorn(cost, mu, nu, 0.1, 20)[0])


def test_distillation_loss_is_zero_for_the_teachers_own_plan_and_positive_otherwise():
    torch.manual_seed(0)
    teacher = torch.randn(2, 6, 9).log_softmax(-1)
    student = torch.randn(2, 6, 9, requires_grad=True)
    assert torch.allclose(distillation_loss(teacher, teacher), torch.zeros(2), atol=1e-6)
    loss = distillation_loss(student, teacher)
    assert loss.shape == (2,) and (loss > 0).all()
    loss.sum().backward()
    assert student.grad.abs().sum() > 0
