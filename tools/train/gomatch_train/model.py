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

from .attention import Attention, coordinate_neighbours
from .classifier import MatchClassifier
from .config import ModelConfig
from .encoder import PointResNet
from .sinkhorn import cost_with_dustbins, descriptor_distances, marginals, mutual_assignment, transport


@dataclass
class MatchResult:
    """Everything a forward pass produces for one sample. Matrices are (N3+1, N2+1), 3D rows."""

    desc2d: torch.Tensor  # (N2, C) L2-normalised final 2D features
    desc3d: torch.Tensor  # (N3, C) L2-normalised final 3D features
    cost: torch.Tensor  # Sinkhorn input: distances plus dustbins
    log_plan: torch.Tensor  # log of the Sinkhorn transport plan
    sinkhorn_iterations: int
    i3d: torch.Tensor  # (M,) 3D index of each proposed match, row-major order
    i2d: torch.Tensor  # (M,) 2D index of each proposed match
    cls_logits: torch.Tensor  # (M,) classifier logits

    @property
    def plan(self) -> torch.Tensor:
        return self.log_plan.exp()

    @property
    def match_probs(self) -> torch.Tensor:
        return torch.sigmoid(self.cls_logits)


class RawMatcher(nn.Module):
    """Encoder, attention and optimal transport: points -> (normalised features, log plan)."""

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
        desc2d, desc3d = self.kp2d_enc(pts2d), self.kp3d_enc(pts3d)
        desc2d, desc3d = self.attention(desc2d, desc3d, neighbours2d, neighbours3d)
        desc2d = F.normalize(desc2d, p=2, dim=1)
        desc3d = F.normalize(desc3d, p=2, dim=1)
        cost = cost_with_dustbins(descriptor_distances(desc3d, desc2d), self.bin_score)
        mu, nu = marginals(desc3d.shape[0], desc2d.shape[0], cost)
        log_plan, iterations = transport(cost, mu, nu, self.config.sinkhorn_eps, self.config.sinkhorn_iters)
        return desc2d, desc3d, cost, log_plan, iterations


class Matcher(nn.Module):
    """Raw matcher, mutual assignment on the plan, and the outlier classifier on the proposed matches."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.raw_matcher = RawMatcher(config)
        self.classifier = MatchClassifier(config.feature_dim, config.classifier_blocks)

    def forward(self, pts2d: torch.Tensor, pts3d: torch.Tensor) -> MatchResult:
        desc2d, desc3d, cost, log_plan, iterations = self.raw_matcher(pts2d, pts3d)
        i3d, i2d = mutual_assignment(log_plan.exp())
        logits = self.classifier(desc2d, desc3d, i2d, i3d)
        return MatchResult(desc2d, desc3d, cost, log_plan, iterations, i3d, i2d, logits)


class GoMatch(nn.Module):
    """forward(pts2d (N2, 2), pts3d (N3, 2)) -> MatchResult for one query/database-view pair."""

    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        self.config = config
        self.matcher = Matcher(config)

    def forward(self, pts2d: torch.Tensor, pts3d: torch.Tensor) -> MatchResult:
        return self.matcher(pts2d, pts3d)
