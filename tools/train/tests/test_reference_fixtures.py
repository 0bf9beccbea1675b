"""Our model against the reference implementation's recorded outputs (shared/reference/fixtures).

Each stage is checked twice: in isolation (fed the reference's output of the previous stage, tight tolerance) and
end to end (one forward pass from the points, stage outputs captured with hooks). Match indices, the assignment
mask and the number of Sinkhorn iterations must agree exactly.
"""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import FIXTURES, require

from gomatch_train.attention import coordinate_neighbours
from gomatch_train.export import load_export
from gomatch_train.fixture import ATTENTION_STAGES, forward_stages
from gomatch_train.sinkhorn import cost_with_dustbins, descriptor_distances, log_sinkhorn, marginals, mutual_assignment

STAGE_TOLERANCE = 2e-5  # isolated stage: max |ours - ref| <= tol * max(1, max |ref|)
ENCODER_TOLERANCE = 1e-4  # 12 residual blocks from the raw points; InstanceNorm over 8 points amplifies rounding
END_TO_END_TOLERANCE = 2e-4  # after 12 encoder blocks and 3 attention layers (float32 rounding accumulates)
PLAN_TOLERANCE = 1e-6  # absolute, transport plan entries (<= 1)
PROB_TOLERANCE = 1e-4  # absolute, classifier probabilities


def fixture_cases():
    if not FIXTURES.is_dir():
        return [None]
    return sorted(p for p in FIXTURES.iterdir() if p.is_dir())


CASES = fixture_cases()


def case_id(path):
    return path.name if path is not None else "fixtures-absent"


class Fixture:
    def __init__(self, path):
        require(path / "index.json")
        self.path = path
        self.index = json.loads((path / "index.json").read_text())

    def array(self, name) -> np.ndarray:
        return np.load(self.path / self.index["arrays"][name]["file"])

    def tensor(self, name) -> torch.Tensor:
        return torch.from_numpy(self.array(name))


@pytest.fixture(scope="module")
def model():
    weights = require(FIXTURES / "weights.safetensors")
    return load_export(str(weights)).eval()


def assert_close(name, ours, ref, rel):
    ours = ours.detach().numpy() if isinstance(ours, torch.Tensor) else ours
    ref = ref.numpy() if isinstance(ref, torch.Tensor) else ref
    assert ours.shape == ref.shape, f"{name}: shape {ours.shape} != reference {ref.shape}"
    err = float(np.abs(ours.astype(np.float64) - ref.astype(np.float64)).max()) if ref.size else 0.0
    bound = rel * max(1.0, float(np.abs(ref).max()) if ref.size else 1.0)
    assert err <= bound, f"{name}: max abs error {err:.3e} > {bound:.3e}"


def assignment_mask(i3d, i2d, n3d, n2d) -> np.ndarray:
    """The reference's mask format: matches, dustbin column 1 - row sum, dustbin row 1 - column sum, cast to bool."""
    mask = np.zeros((n3d + 1, n2d + 1), dtype=np.float32)
    mask[i3d, i2d] = 1
    mask[:, -1] = 1 - mask.sum(1)
    mask[-1, :] = 1 - mask.sum(0)
    mask[-1, -1] = 0
    return mask.astype(bool)


def probs_matrix(i3d, i2d, probs, n3d, n2d) -> np.ndarray:
    out = -np.ones((n3d + 1, n2d + 1), dtype=np.float32)
    out[i3d, i2d] = probs
    return out


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_stages_in_isolation(case, model):
    if case is None:
        require(FIXTURES)
    fx = Fixture(case)
    raw = model.matcher.raw_matcher
    layers = raw.attention.att.layers
    pts2d, pts3d = fx.tensor("pts2d"), fx.tensor("pts3d_bvs")
    n2d, n3d = len(pts2d), len(pts3d)
    with torch.no_grad():
        assert_close("enc2d", raw.kp2d_enc(pts2d), fx.array("enc2d"), ENCODER_TOLERANCE)
        assert_close("enc3d", raw.kp3d_enc(pts3d), fx.array("enc3d"), ENCODER_TOLERANCE)

        nbr2d, nbr3d = coordinate_neighbours(pts2d, raw.config.knn), coordinate_neighbours(pts3d, raw.config.knn)
        previous = ("enc2d", "enc3d")
        for layer, stage in zip(layers, ("att0_self", "att1_cross", "att2_self")):
            out2d, out3d = layer(fx.tensor(previous[0]), fx.tensor(previous[1]), nbr2d, nbr3d)
            assert_close(f"{stage}_2d", out2d, fx.array(f"{stage}_2d"), STAGE_TOLERANCE)
            assert_close(f"{stage}_3d", out3d, fx.array(f"{stage}_3d"), STAGE_TOLERANCE)
            previous = (f"{stage}_2d", f"{stage}_3d")

        assert_close("desc2d_l2", F.normalize(fx.tensor("att2_self_2d"), dim=1), fx.array("desc2d_l2"), STAGE_TOLERANCE)
        assert_close("desc3d_l2", F.normalize(fx.tensor("att2_self_3d"), dim=1), fx.array("desc3d_l2"), STAGE_TOLERANCE)

        desc2d, desc3d = fx.tensor("desc2d_l2"), fx.tensor("desc3d_l2")
        cost = cost_with_dustbins(descriptor_distances(desc3d, desc2d), raw.bin_score)
        assert_close("ot_cost", cost, fx.array("ot_cost"), STAGE_TOLERANCE)

        mu, nu = marginals(n3d, n2d, cost)
        assert_close("ot_mu", mu, fx.array("ot_mu"), 1e-7)
        assert_close("ot_nu", nu, fx.array("ot_nu"), 1e-7)
        eps, iters = raw.config.sinkhorn_eps, raw.config.sinkhorn_iters
        log_plan, iterations = log_sinkhorn(fx.tensor("ot_cost"), mu, nu, eps, iters)
        assert iterations == fx.index["sinkhorn"]["iterations_run"]
        assert_close("scores", log_plan.exp(), fx.array("scores"), PLAN_TOLERANCE)

        i3d, i2d = mutual_assignment(fx.tensor("scores"))
        np.testing.assert_array_equal(i3d.numpy(), fx.array("match_i3d"))
        np.testing.assert_array_equal(i2d.numpy(), fx.array("match_i2d"))
        np.testing.assert_array_equal(assignment_mask(i3d, i2d, n3d, n2d), fx.array("mutual_mask"))

        i3d, i2d = torch.from_numpy(fx.array("match_i3d")), torch.from_numpy(fx.array("match_i2d"))
        dup = 2 if len(i3d) == 1 else 1
        assert_close("cls_in_f2d", desc2d[i2d.repeat(dup)], fx.array("cls_in_f2d"), 0.0)
        assert_close("cls_in_f3d", desc3d[i3d.repeat(dup)], fx.array("cls_in_f3d"), 0.0)
        probs = torch.sigmoid(model.matcher.classifier(desc2d, desc3d, i2d, i3d))
        assert_close("match_probs", probs, fx.array("match_probs"), PROB_TOLERANCE)


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_end_to_end(case, model):
    if case is None:
        require(FIXTURES)
    fx = Fixture(case)
    stages, iterations = forward_stages(model, fx.tensor("pts2d"), fx.tensor("pts3d_bvs"))

    # The shared encoder runs twice: 2D first, then 3D.
    features = ["enc2d", "enc3d"] + [f"{stage}_{side}" for stage in ATTENTION_STAGES for side in ("2d", "3d")]
    for name in features + ["desc2d_l2", "desc3d_l2", "ot_cost"]:
        assert_close(name, stages[name], fx.array(name), END_TO_END_TOLERANCE)
    assert iterations == fx.index["sinkhorn"]["iterations_run"]
    assert_close("scores", stages["scores"], fx.array("scores"), PLAN_TOLERANCE * 10)

    n3d, n2d = stages["scores"].shape[0] - 1, stages["scores"].shape[1] - 1
    np.testing.assert_array_equal(stages["match_i3d"], fx.array("match_i3d"))
    np.testing.assert_array_equal(stages["match_i2d"], fx.array("match_i2d"))
    i3d, i2d = stages["match_i3d"], stages["match_i2d"]
    np.testing.assert_array_equal(assignment_mask(i3d, i2d, n3d, n2d), fx.array("mutual_mask"))
    assert_close("match_probs", stages["match_probs"], fx.array("match_probs"), PROB_TOLERANCE)
    probs = probs_matrix(i3d, i2d, stages["match_probs"], n3d, n2d)
    assert_close("match_probs_matrix", probs, fx.array("match_probs_matrix"), PROB_TOLERANCE)


SMALL_SET = 12  # below this many points the reference's BLAS switches summation path (see README, Conformance)


def ordered_linear(x: torch.Tensor, layer, fused: bool) -> torch.Tensor:
    """A per-point linear layer summed over the inputs in order, in f32: with fused multiply-add and the bias
    added last (`fused`), or with separate multiply and add starting from the bias. The f32 FMA is emulated in
    f64, where the product of two f32 is exact."""
    w, b = layer.matrix(), layer.bias
    if fused:
        acc = torch.zeros(x.shape[0], w.shape[0])
        for k in range(w.shape[1]):
            acc = (acc.double() + x[:, k : k + 1].double() * w[:, k].double()).float()
        return acc + b
    acc = torch.zeros(x.shape[0], w.shape[0]) + b
    for k in range(w.shape[1]):
        acc = acc + x[:, k : k + 1] * w[:, k]
    return acc


def pytorch_instance_norm(y: torch.Tensor) -> torch.Tensor:
    """PyTorch's CPU instance norm over the rows of (N, C): f64 sums, f32 mean and variance, x * scale + offset
    fused (core/src/nn/norm.rs computes the same)."""
    n = y.shape[0]
    mean = (y.double().sum(0) / n).float()
    variance = ((y - mean) ** 2).double().sum(0).float() / np.float32(n)
    scale = (1 / torch.sqrt(variance.double() + 1e-5)).float()
    offset = -(mean * scale)
    return (y.double() * scale.double() + offset.double()).float()


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_reference_encoder_arithmetic(case, model):
    """The arithmetic the Rust core follows reproduces the reference encoder bit for bit: unfolded residual
    blocks, ordered fused multiply-adds, PyTorch's instance norm; sets under SMALL_SET points need the
    reference BLAS's small-matrix path (plain multiply-adds, bias first), which the Rust core follows there too."""
    if case is None:
        require(FIXTURES)
    fx = Fixture(case)
    encoder = model.matcher.raw_matcher.kp2d_enc
    with torch.no_grad():
        for points, stage in (("pts2d", "enc2d"), ("pts3d_bvs", "enc3d")):
            x = fx.tensor(points)
            fused = len(x) >= SMALL_SET
            x = ordered_linear(x, encoder.conv_in[0], fused)
            for i in range(encoder.blocks):
                block = getattr(encoder, f"conv_{i}")
                y = ordered_linear(ordered_linear(x, block.preconv[0], fused), block.conv1[0], fused)
                y = pytorch_instance_norm(ordered_linear(pytorch_instance_norm(y), block.conv2[0], fused))
                x = torch.relu(y) + x
            np.testing.assert_array_equal(x.numpy(), fx.array(stage), err_msg=f"{case.name} {stage}")
