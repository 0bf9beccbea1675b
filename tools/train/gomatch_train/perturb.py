"""A control for quantisation checks: the export with every weight multiplied by (1 + u), u uniform in
[-rel, rel], seeded. At rel = 2^-11 (the default) the perturbation is the size of f16 rounding, so comparing the
evaluation of such copies with the original's shows how much a metric moves under any tiny weight change, with no
quantiser involved (model card, "Validation").

    python -m gomatch_train.perturb EXPORT.safetensors OUT.safetensors [--relative 0.00048828125] [--seed 0]

The shared encoder's two copies receive the same perturbation, so the output is a valid export.
"""

import argparse

import torch

from .export import load_export, save_export
from .model import GoMatch

F16_RELATIVE_STEP = 2.0**-11  # f16 has 10 stored mantissa bits: a relative rounding step of 2^-10, half of it at most


def perturbed(model: GoMatch, relative: float, seed: int) -> GoMatch:
    """The model with each parameter scaled elementwise by 1 + U(-relative, relative) (generator seeded by `seed`)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in model.parameters():
            noise = torch.rand(parameter.shape, generator=generator, dtype=torch.float64) * 2.0 - 1.0
            parameter.mul_((1.0 + relative * noise).to(parameter.dtype))
    return model


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("export")
    p.add_argument("out")
    p.add_argument("--relative", type=float, default=F16_RELATIVE_STEP)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    save_export(perturbed(load_export(args.export), args.relative, args.seed), args.out)


if __name__ == "__main__":
    main()
