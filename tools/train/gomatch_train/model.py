"""GoMatch, variant "BVs" (both sets are 2-D bearing coordinates, one shared encoder).

Pipeline of one forward pass (one query image against one database view):
    encoder -> attention (self, cross, self) -> L2 normalisation -> cost with dustbins -> log-domain Sinkhorn
    -> mutual assignment -> outlier classifier.
Module names reproduce the reference checkpoint's state_dict names (`matcher.raw_matcher.*`,
`matcher.classifier.*`); the shared encoder is registered twice (`kp2d_enc`, `kp3d_enc`) as in the reference.
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.rnn import pad_sequence

from .attention import Attention, coordinate_neighbours
from .classifier import MatchClassifier
from .config import ModelConfig
from .encoder import PointResNet
from .layers import at_least_float32, on_both_sets
from .sinkhorn import cost_with_dustbins, descriptor_distances, marginals, mutual_assignment, transport


@dataclass
class MatchResult:
    """Everything a forward pass produces for one sample. Matrices are (N3+1, N2+1), 3D rows. For a batch
    (`forward_batch`) every tensor has a leading dimension B and the matches are padded to the largest count."""

    desc2d: torch.Tensor  # (N2, C) L2-normalised final 2D features
    desc3d: torch.Tensor  # (N3, C) L2-normalised final 3D features
    cost: torch.Tensor  # Sinkhorn input: distances plus dustbins
    log_plan: torch.Tensor  # log of the Sinkhorn transport plan
    sinkhorn_iterations: int
    i3d: torch.Tensor  # (M,) 3D index of each proposed match, row-major order
    i2d: torch.Tensor  # (M,) 2D index of each proposed match
    cls_logits: torch.Tensor  # (M,) classifier logits
    valid: torch.Tensor  # (M,) true for a real match (false only for a batch's padding)

    @property
    def plan(self) -> torch.Tensor:
        return self.log_plan.exp()

    @property
    def match_probs(self) -> torch.Tensor:
        return torch.sigmoid(self.cls_logits)


class RawMatcher(nn.Module):
    """Encoder, attention and optimal transport: points -> (normalised features, log plan), for one sample or a
    batch of equal-size samples (leading dimension B)."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.kp2d_enc = PointResNet(2, config.feature_dim, config.encoder_blocks)
        self.kp3d_enc = self.kp2d_enc
        self.bin_score = nn.Parameter(torch.tensor(1.0))
        self.attention = Attention(config.feature_dim, config.heads)

    def forward(self, pts2d: torch.Tensor, pts3d: torch.Tensor):
        neighbours2d = coordinate_neighbours(pts2d, self.config.knn)
        neighbours3d = coordinate_neighbours(pts3d, self.config.knn)
        if pts2d.dim() == 2:
            desc2d, desc3d = self.kp2d_enc(pts2d), self.kp3d_enc(pts3d)
        else:  # the encoder is shared: one stacked pass where the sets have the same size
            desc2d, desc3d = on_both_sets(self.kp2d_enc, pts2d, pts3d)
        desc2d, desc3d = self.attention(desc2d, desc3d, neighbours2d, neighbours3d)
        desc2d = F.normalize(at_least_float32(desc2d), p=2, dim=-1)
        desc3d = F.normalize(at_least_float32(desc3d), p=2, dim=-1)
        with torch.autocast(desc2d.device.type, enabled=False):  # the matching layer in float32 (bf16 training)
            cost = cost_with_dustbins(descriptor_distances(desc3d, desc2d), self.bin_score)
            mu, nu = marginals(desc3d.shape[-2], desc2d.shape[-2], cost)
            log_plan, iterations = transport(cost, mu, nu, self.config.sinkhorn_eps, self.config.sinkhorn_iters)
        return desc2d, desc3d, cost, log_plan, iterations


class Matcher(nn.Module):
    """Raw matcher, mutual assignment on the plan, and the outlier classifier on the proposed matches."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.raw_matcher = RawMatcher(config)
        self.classifier = MatchClassifier(config.feature_dim, config.classifier_blocks)

    def forward(self, pts2d: torch.Tensor, pts3d: torch.Tensor) -> MatchResult:
        return self.classify(*self.raw_matcher(pts2d, pts3d))

    def forward_batch(self, pts2d: torch.Tensor, pts3d: torch.Tensor) -> MatchResult:
        """The batched MatchResult of (B, N2, 2), (B, N3, 2); the Sinkhorn iterations run until every sample has
        converged, the mutual assignment runs per sample, the classifier on the padded matches."""
        desc2d, desc3d, cost, log_plan, iterations = self.raw_matcher(pts2d, pts3d)
        pairs = [mutual_assignment(plan) for plan in log_plan.detach().exp()]
        i3d = pad_sequence([i3d for i3d, _ in pairs], batch_first=True)
        i2d = pad_sequence([i2d for _, i2d in pairs], batch_first=True)
        counts = torch.tensor([len(i3d) for i3d, _ in pairs], device=i3d.device)
        valid = torch.arange(i3d.shape[1], device=i3d.device) < counts.unsqueeze(1)
        logits = self.classifier.forward_batch(desc2d, desc3d, i2d, i3d, valid)
        return MatchResult(desc2d, desc3d, cost, log_plan, iterations, i3d, i2d, logits, valid)

    def classify(self, desc2d, desc3d, cost, log_plan, iterations) -> MatchResult:
        """Mutual assignment on one sample's plan and the classifier on its matches."""
        i3d, i2d = mutual_assignment(log_plan.exp())
        logits = self.classifier(desc2d, desc3d, i2d, i3d)
        valid = torch.ones_like(i3d, dtype=torch.bool)
        return MatchResult(desc2d, desc3d, cost, log_plan, iterations, i3d, i2d, logits, valid)


class GoMatch(nn.Module):
    """forward(pts2d (N2, 2), pts3d (N3, 2)) -> MatchResult for one query/database-view pair."""

    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        self.config = config
        self.matcher = Matcher(config)

    def forward(self, pts2d: torch.Tensor, pts3d: torch.Tensor) -> MatchResult:
        return self.matcher(pts2d, pts3d)

    def forward_batch(self, pts2d: torch.Tensor, pts3d: torch.Tensor) -> MatchResult:
        """forward for a batch of equal-size samples (B, N2, 2), (B, N3, 2) -> batched MatchResult."""
        return self.matcher.forward_batch(pts2d, pts3d)
