"""Per-sample losses and matching metrics, shared by training steps and validation."""

from dataclasses import dataclass, field

import torch

from .loss import classifier_labels, classifier_loss, distillation_loss, match_loss
from .model import MatchResult


@dataclass
class SampleOutcome:
    match_loss: torch.Tensor
    cls_loss: torch.Tensor
    proposed: int  # matches given by the mutual assignment
    proposed_correct: int  # ... of which are GT matches
    gt_matches: int
    kept: int  # proposed matches with classifier probability > threshold
    kept_correct: int
    distill_loss: torch.Tensor | float = 0.0  # weighted distillation term (`--teacher`), 0 without a teacher

    @property
    def loss(self) -> torch.Tensor:
        """Paper sec. 4.2: L_total = L_match + L_or (+ the weighted distillation term with a teacher)."""
        return self.match_loss + self.cls_loss + self.distill_loss


def assess(result: MatchResult, match: torch.Tensor, threshold: float) -> SampleOutcome:
    """Losses and match counts of one forward pass against the GT `match` (N2,) (3D index or -1)."""
    return assess_batch(result, match, threshold)[0]


def assess_batch(
    result: MatchResult, match: torch.Tensor, threshold: float, teacher: MatchResult | None = None, weight: float = 0.0
) -> list:
    """`assess` for every sample of a batched result (`GoMatch.forward_batch`) and GT (B, N2); one sync. With a
    `teacher`'s result on the same samples, each outcome adds `weight` x the distillation loss."""
    labels = classifier_labels(result.i3d, result.i2d, match) * result.valid
    kept = (result.match_probs.detach() > threshold) & result.valid
    match_losses = match_loss(result.log_plan, match).reshape(-1)
    cls_losses = classifier_loss(result.cls_logits, labels, result.valid).reshape(-1)
    distill_losses = (
        weight * distillation_loss(result.log_plan, teacher.log_plan).reshape(-1)
        if teacher is not None
        else [0.0] * len(match_losses)
    )
    counts = torch.stack(
        [result.valid.sum(-1), labels.sum(-1), (match >= 0).sum(-1), kept.sum(-1), (kept & (labels > 0)).sum(-1)],
        dim=-1,
    )
    return [
        SampleOutcome(match_losses[b], cls_losses[b], *(int(c) for c in sample_counts), distill_losses[b])
        for b, sample_counts in enumerate(counts.reshape(-1, 5).tolist())
    ]


def ratio(num: float, den: float) -> float:
    return num / den if den > 0 else 0.0


@dataclass
class Totals:
    """Sums over samples; precision/recall are micro-averages (pooled counts)."""

    samples: int = 0
    match_loss: float = 0.0
    cls_loss: float = 0.0
    distill_loss: float = 0.0
    counts: dict = field(
        default_factory=lambda: dict(proposed=0, proposed_correct=0, gt_matches=0, kept=0, kept_correct=0)
    )

    def add(self, outcome: SampleOutcome) -> None:
        self.samples += 1
        self.match_loss += outcome.match_loss.item()
        self.cls_loss += outcome.cls_loss.item()
        self.distill_loss += torch.as_tensor(outcome.distill_loss).item()
        for key in self.counts:
            self.counts[key] += getattr(outcome, key)

    def merge(self, other: "Totals") -> None:
        self.samples += other.samples
        self.match_loss += other.match_loss
        self.cls_loss += other.cls_loss
        self.distill_loss += other.distill_loss
        for key in self.counts:
            self.counts[key] += other.counts[key]

    def to_tensor(self) -> torch.Tensor:
        values = [self.samples, self.match_loss, self.cls_loss, self.distill_loss] + [self.counts[k] for k in self.counts]
        return torch.tensor(values, dtype=torch.float64)

    @classmethod
    def from_tensor(cls, t: torch.Tensor) -> "Totals":
        totals = cls()
        values = t.tolist()
        totals.samples, totals.match_loss, totals.cls_loss, totals.distill_loss = int(values[0]), *values[1:4]
        for key, value in zip(totals.counts, values[4:]):
            totals.counts[key] = int(value)
        return totals

    def summary(self) -> dict:
        c = self.counts
        n = max(self.samples, 1)
        return {
            "samples": self.samples,
            "loss": (self.match_loss + self.cls_loss) / n,
            "match_loss": self.match_loss / n,
            "cls_loss": self.cls_loss / n,
            "distill_loss": self.distill_loss / n,
            "match_precision": ratio(c["proposed_correct"], c["proposed"]),
            "match_recall": ratio(c["proposed_correct"], c["gt_matches"]),
            "cls_precision": ratio(c["kept_correct"], c["kept"]),
            "cls_recall": ratio(c["kept_correct"], c["proposed_correct"]),
            "matches_per_sample": c["proposed"] / n,
        }
