"""Controls for quantisation checks: the export with its weights changed by a known, small amount, written as
a valid export (model card, "Validation").

- noise (default): every weight multiplied by (1 + u), u uniform in [-rel, rel], seeded. At rel = 2^-11 the
  change is the size of f16 rounding, with no quantiser involved.
- `--round f16`: every parameter rounded to the nearest f16 value; `--round int8`: every weight matrix rounded
  to 255 levels per output row (symmetric scale max|w| / 127, round to nearest; biases and the dustbin score
  kept), the plain rounding that the converter's GPTQ rounding improves on.
- `--only GROUP` changes one part of the network: `input` (the point encoder's first layer), `encoder` (the
  point encoder), `attention`, `classifier`; everything else stays bit-identical.

    python -m gomatch_train.perturb EXPORT.safetensors OUT.safetensors [--relative 0.00048828125] [--seed 0]
    python -m gomatch_train.perturb EXPORT.safetensors OUT.safetensors --round f16|int8 [--only GROUP]

The shared encoder's two copies receive the same change, so the output is a valid export.
"""

import argparse

import torch

from .export import load_export, save_export
from .model import GoMatch

F16_RELATIVE_STEP = 2.0**-11  # f16 has 10 stored mantissa bits: a relative rounding step of 2^-10, half of it at most
INT8_LEVELS = 127
GROUPS = {
    "all": "matcher.",
    "input": "matcher.raw_matcher.kp2d_enc.conv_in.",
    "encoder": "matcher.raw_matcher.kp2d_enc.",
    "attention": "matcher.raw_matcher.attention.",
    "classifier": "matcher.classifier.",
}


def selected(model: GoMatch, group: str) -> list[torch.nn.Parameter]:
    """The parameters of one group, in the model's order."""
    return [p for name, p in model.named_parameters() if name.startswith(GROUPS[group])]


def perturbed(model: GoMatch, relative: float, seed: int, group: str = "all") -> GoMatch:
    """The model with each parameter of `group` scaled elementwise by 1 + U(-relative, relative) (generator
    seeded by `seed`)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in selected(model, group):
            noise = torch.rand(parameter.shape, generator=generator, dtype=torch.float64) * 2.0 - 1.0
            parameter.mul_((1.0 + relative * noise).to(parameter.dtype))
    return model


def int8_rounded(weight: torch.Tensor) -> torch.Tensor:
    """Symmetric per-output-row rounding to 2 * 127 + 1 levels (an all-zero row stays zero)."""
    rows = weight.reshape(weight.shape[0], -1)
    scale = rows.abs().amax(dim=1, keepdim=True) / INT8_LEVELS
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    return (torch.round(rows / scale).clamp(-INT8_LEVELS, INT8_LEVELS) * scale).reshape(weight.shape)


def rounded(model: GoMatch, precision: str, group: str = "all") -> GoMatch:
    """The model with the parameters of `group` rounded to f16, or its weight matrices to int8 levels."""
    with torch.no_grad():
        for parameter in selected(model, group):
            if precision == "f16":
                parameter.copy_(parameter.to(torch.float16).to(parameter.dtype))
            elif parameter.dim() >= 2:
                parameter.copy_(int8_rounded(parameter))
    return model


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("export")
    p.add_argument("out")
    p.add_argument("--relative", type=float, default=F16_RELATIVE_STEP)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--round", choices=["f16", "int8"], help="round instead of adding noise")
    p.add_argument("--only", choices=sorted(GROUPS), default="all", help="the part of the network to change")
    args = p.parse_args(argv)
    model = load_export(args.export)
    if args.round:
        model = rounded(model, args.round, args.only)
    else:
        model = perturbed(model, args.relative, args.seed, args.only)
    save_export(model, args.out)


if __name__ == "__main__":
    main()
