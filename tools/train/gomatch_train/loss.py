"""Training losses (paper sec. 4.2): matching loss (eq. 2) + outlier rejection loss (eq. 3).

Ground truth per sample is `match` (N2,): for each 2D keypoint the index of its 3D point, or -1 (unmatched).
"""

import torch
import torch.nn.functional as F


def match_loss(log_plan: torch.Tensor, match: torch.Tensor) -> torch.Tensor:
    """Eq. 2: -1/N_m (sum log P over GT matches + unmatched 2D in the dustbin row + unmatched 3D in the dustbin
    column), N_m the number of those entries. Uses log P from the log-domain Sinkhorn directly. Per sample of a
    batch for (B, N3+1, N2+1) plans and (B, N2) matches."""
    n3d = log_plan.shape[-2] - 1
    matched = match >= 0
    # Each keypoint's term: its GT 3D point's row, or the dustbin row.
    rows = torch.where(matched, match, n3d).unsqueeze(-2)
    terms2d = log_plan[..., :, :-1].gather(-2, rows).squeeze(-2)
    has_match3d = torch.zeros(log_plan.shape[:-2] + (n3d + 1,), dtype=torch.bool, device=match.device)
    has_match3d.scatter_(-1, torch.where(matched, match, n3d), True)
    unmatched3d = ~has_match3d[..., :-1]
    terms3d = torch.where(unmatched3d, log_plan[..., :-1, -1], 0.0)
    count = match.shape[-1] + unmatched3d.sum(dim=-1)
    return -(terms2d.sum(dim=-1) + terms3d.sum(dim=-1)) / count


def classifier_labels(i3d: torch.Tensor, i2d: torch.Tensor, match: torch.Tensor) -> torch.Tensor:
    """1.0 where the proposed match (i3d, i2d) is a GT match, else 0.0 (per sample for (B, M) and (B, N2))."""
    return (match.gather(-1, i2d) == i3d).float()


def classifier_loss(logits: torch.Tensor, labels: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 3: mean weighted binary cross-entropy over the N_c matches given to the classifier.

    Positives are weighted by #negatives / #positives and negatives by 1, as in the reference; without any
    positive the loss is zero. For a batch (B, M), one loss per sample over its `valid` matches.
    """
    weight = valid.to(logits.dtype) if valid is not None else torch.ones_like(logits)
    labels = labels * weight
    positives = labels.sum(dim=-1, keepdim=True)
    count = weight.sum(dim=-1, keepdim=True)
    weights = ((count - positives) / positives.clamp_min(1.0) * labels + (1.0 - labels)) * weight
    bce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    loss = (weights * bce).sum(dim=-1, keepdim=True) / count.clamp_min(1.0)
    return torch.where(positives > 0, loss, 0.0 * loss).squeeze(-1)


def distillation_loss(log_plan: torch.Tensor, teacher_log_plan: torch.Tensor) -> torch.Tensor:
    """Knowledge distillation of a teacher's assignment (Hinton et al. 2015, on the Sinkhorn plan of sec. 3.3):
    each keypoint's distribution over the 3D points and the dustbin (a plan column, normalised) and each 3D
    point's over the keypoints and the dustbin (a row) should be the teacher's; the mean Kullback-Leibler
    divergence KL(teacher || student) over those N2 + N3 distributions, per sample of a batch of (B, N3+1, N2+1)
    plans. Zero when the plans agree; the teacher's soft plan carries the near misses a one-hot GT lacks."""
    teacher = teacher_log_plan.detach()

    def divergence(student: torch.Tensor, target: torch.Tensor, dim: int) -> torch.Tensor:
        target = target.log_softmax(dim)
        return (target.exp() * (target - student.log_softmax(dim))).sum(dim)

    columns = divergence(log_plan[..., :-1], teacher[..., :-1], -2)
    rows = divergence(log_plan[..., :-1, :], teacher[..., :-1, :], -1)
    return (columns.sum(-1) + rows.sum(-1)) / (columns.shape[-1] + rows.shape[-1])
