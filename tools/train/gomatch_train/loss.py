"""Training losses (paper sec. 4.2): matching loss (eq. 2) + outlier rejection loss (eq. 3).

Ground truth per sample is `match` (N2,): for each 2D keypoint the index of its 3D point, or -1 (unmatched).
"""

import torch
import torch.nn.functional as F


def match_loss(log_plan: torch.Tensor, match: torch.Tensor) -> torch.Tensor:
    """Eq. 2: -1/N_m (sum log P over GT matches + unmatched 2D in the dustbin row + unmatched 3D in the dustbin
    column), N_m the number of those entries. Uses log P from the log-domain Sinkhorn directly."""
    n3d, n2d = log_plan.shape[0] - 1, log_plan.shape[1] - 1
    matched = match >= 0
    i2d = torch.nonzero(matched).squeeze(1)
    i3d = match[matched]
    unmatched2d = torch.nonzero(~matched).squeeze(1)
    has_match3d = torch.zeros(n3d, dtype=torch.bool, device=match.device)
    has_match3d[i3d] = True
    unmatched3d = torch.nonzero(~has_match3d).squeeze(1)
    terms = torch.cat([log_plan[i3d, i2d], log_plan[n3d, unmatched2d], log_plan[unmatched3d, n2d]])
    return -terms.mean()


def classifier_labels(i3d: torch.Tensor, i2d: torch.Tensor, match: torch.Tensor) -> torch.Tensor:
    """1.0 where the proposed match (i3d, i2d) is a GT match, else 0.0."""
    return (match[i2d] == i3d).float()


def classifier_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Eq. 3: mean weighted binary cross-entropy over the N_c matches given to the classifier.

    Positives are weighted by #negatives / #positives and negatives by 1, as in the reference; without any
    positive the loss is zero.
    """
    positives = labels.sum()
    if positives == 0:
        return logits.sum() * 0.0
    weights = (labels.numel() - positives) / positives * labels + (1.0 - labels)
    bce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    return (weights * bce).mean()
