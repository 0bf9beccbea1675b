"""Model configuration: the hyper-parameters that fix the network's shape and inference behaviour.

Stored in exported checkpoints as the `__metadata__` entry `gomatch_config` (JSON), which the Rust converter reads.
"""

import json
from dataclasses import asdict, dataclass, fields


@dataclass(frozen=True)
class ModelConfig:
    feature_dim: int = 128  # width of keypoint features, attention and classifier trunk
    encoder_blocks: int = 12  # residual blocks of the shared point encoder
    classifier_blocks: int = 4  # residual blocks of the outlier classifier
    heads: int = 4  # cross-attention heads (feature_dim must be divisible)
    knn: int = 10  # neighbours of the EdgeConv self attention
    sinkhorn_iters: int = 20  # maximum Sinkhorn iterations
    sinkhorn_eps: float = 0.1  # entropic regularisation
    match_threshold: float = 0.5  # classifier probability above which a match is kept (inference)

    def __post_init__(self):
        if self.feature_dim % self.heads != 0:
            raise ValueError(f"feature_dim {self.feature_dim} is not divisible by heads {self.heads}")
        for name in ("feature_dim", "encoder_blocks", "heads", "knn", "sinkhorn_iters"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "ModelConfig":
        values = json.loads(text)
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown gomatch_config keys: {sorted(unknown)}")
        return cls(**values)
