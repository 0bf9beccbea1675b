"""gomatch_train.perturb: seeded relative weight noise of a given size, written as a valid export."""

import torch

from gomatch_train.config import ModelConfig
from gomatch_train.export import load_export, save_export
from gomatch_train.model import GoMatch
from gomatch_train.perturb import F16_RELATIVE_STEP, GROUPS, main


def test_every_weight_moves_within_the_relative_bound_and_the_seed_fixes_the_noise(tmp_path):
    torch.manual_seed(0)
    source = tmp_path / "model.safetensors"
    save_export(GoMatch(ModelConfig(feature_dim=16, encoder_blocks=1, classifier_blocks=1)), str(source))
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        main([str(source), str(tmp_path / f"{name}.safetensors"), "--seed", str(seed)])

    original = load_export(str(source)).state_dict()
    a, b, c = (load_export(str(tmp_path / f"{n}.safetensors")).state_dict() for n in "abc")  # loads: encoders equal
    moved = 0
    for name, w in original.items():
        ratio = a[name][w != 0] / w[w != 0]
        assert torch.all((ratio - 1).abs() <= F16_RELATIVE_STEP * (1 + 1e-6)), name
        moved += int((a[name] != w).sum())
        assert torch.equal(a[name], b[name]), name
    assert moved > 0.9 * sum(w.numel() for w in original.values())
    assert any(not torch.equal(a[name], c[name]) for name in original)


def test_rounding_one_group_leaves_every_other_parameter_bit_identical(tmp_path):
    torch.manual_seed(0)
    source = tmp_path / "model.safetensors"
    save_export(GoMatch(ModelConfig(feature_dim=16, encoder_blocks=1, classifier_blocks=1)), str(source))
    main([str(source), str(tmp_path / "f16.safetensors"), "--round", "f16", "--only", "attention"])
    main([str(source), str(tmp_path / "int8.safetensors"), "--round", "int8", "--only", "classifier"])

    original = load_export(str(source)).state_dict()
    f16 = load_export(str(tmp_path / "f16.safetensors")).state_dict()
    int8 = load_export(str(tmp_path / "int8.safetensors")).state_dict()
    for name, w in original.items():
        if name.startswith(GROUPS["attention"]):
            assert torch.equal(f16[name], w.half().float()), name
        else:
            assert torch.equal(f16[name], w), name
        if name.startswith(GROUPS["classifier"]) and w.dim() >= 2:
            rows = int8[name].reshape(w.shape[0], -1)
            scale = w.reshape(w.shape[0], -1).abs().amax(dim=1, keepdim=True) / 127
            levels = rows / scale
            assert torch.allclose(levels, levels.round(), atol=1e-3) and levels.abs().max() <= 127 + 1e-3, name
            assert torch.all((rows - w.reshape(w.shape[0], -1)).abs() <= scale / 2 * (1 + 1e-5)), name
        else:
            assert torch.equal(int8[name], w), name
    assert any(not torch.equal(f16[n], original[n]) for n in original if n.startswith(GROUPS["attention"]))
    assert any(not torch.equal(int8[n], original[n]) for n in original if n.startswith(GROUPS["classifier"]))
