"""Training: the loss goes down on a tiny synthetic sample; the CLI trains, exports and resumes exactly."""

import json

import numpy as np
import pytest
import torch
from safetensors import safe_open

from gomatch_train import train, validate
from gomatch_train.config import ModelConfig
from gomatch_train.dataset import Sample, load_samples
from gomatch_train.evaluate import assess, assess_batch
from gomatch_train.export import load_export
from gomatch_train.model import GoMatch
from gomatch_train.synthetic import random_sample

TINY = ["--feature-dim", "32", "--encoder-blocks", "2", "--classifier-blocks", "1"]


def test_a_few_adam_steps_reduce_the_loss_on_one_sample():
    torch.manual_seed(0)
    pts2d, pts3d, match = random_sample(np.random.default_rng(0), 90, 60, 30)
    pts2d, pts3d, match = torch.from_numpy(pts2d), torch.from_numpy(pts3d), torch.from_numpy(match)
    model = GoMatch(ModelConfig(feature_dim=32, encoder_blocks=2, classifier_blocks=1))
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(15):
        optimizer.zero_grad()
        outcome = assess(model(pts2d, pts3d), match, 0.5)
        outcome.loss.backward()
        optimizer.step()
        losses.append(outcome.loss.item())
    assert all(np.isfinite(losses))
    assert losses[-1] < losses[0] - 0.1, losses


def cli(data, out, *extra):
    return [
        "--train", str(data / "train.safetensors"), "--val", str(data / "val.safetensors"), "--out", str(out),
        "--epochs", "2", "--batch", "2", "--max-points", "64", "--min-points", "20", "--log-every", "1", *TINY,
        *extra,
    ]  # fmt: skip


def exported(path):
    with safe_open(str(path), "pt") as f:
        return {name: f.get_tensor(name) for name in f.keys()}


def test_cli_trains_exports_and_resumes_exactly(data, tmp_path, capsys):
    straight = tmp_path / "straight"
    train.main(cli(data, straight))
    out = capsys.readouterr().out
    assert "epoch 1 validation: loss" in out and "samples/s" in out

    history = [json.loads(line) for line in (straight / "history.jsonl").read_text().splitlines()]
    assert [h["epoch"] for h in history] == [0, 1]
    assert {"loss", "match_precision", "match_recall", "cls_precision", "cls_recall"} <= set(history[0])
    best = load_export(str(straight / "best.safetensors"))
    assert best.config == ModelConfig(feature_dim=32, encoder_blocks=2, classifier_blocks=1)

    # Interrupted run: stop after 2 optimizer steps (mid epoch 0: 3 batches per epoch), then resume twice.
    resumed = tmp_path / "resumed"
    train.main(cli(data, resumed, "--max-steps", "2"))
    assert "stopping at step 2" in capsys.readouterr().out
    train.main(cli(data, resumed, "--resume", "--max-steps", "4"))
    train.main(cli(data, resumed, "--resume"))
    assert "resumed" in capsys.readouterr().out

    a, b = exported(straight / "last.safetensors"), exported(resumed / "last.safetensors")
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed run diverged from the uninterrupted run"
    assert (resumed / "history.jsonl").read_text() == (straight / "history.jsonl").read_text()


def test_heads_and_sinkhorn_iterations_are_options_the_export_records(data, tmp_path):
    out = tmp_path / "device"
    train.main(cli(data, out, "--max-steps", "1", "--heads", "2", "--sinkhorn-iters", "10"))
    config = load_export(str(out / "last.safetensors")).config
    assert (config.heads, config.sinkhorn_iters) == (2, 10)
    with pytest.raises(SystemExit, match="--heads"):
        train.main(cli(data, out, "--resume", "--heads", "4", "--sinkhorn-iters", "10"))


def test_resume_refuses_changed_options(data, tmp_path):
    out = tmp_path / "run"
    train.main(cli(data, out, "--max-steps", "1"))
    with pytest.raises(SystemExit, match="--lr"):
        train.main(cli(data, out, "--resume", "--lr", "0.01"))


def test_validate_cli_reports_the_training_validation_metrics(data, tmp_path, capsys):
    out = tmp_path / "run"
    train.main(cli(data, out, "--epochs", "1"))
    capsys.readouterr()
    validate.main([str(out / "best.safetensors"), str(data / "val.safetensors"), "--max-points", "64"])
    reported = json.loads(capsys.readouterr().out)
    recorded = json.loads((out / "history.jsonl").read_text().splitlines()[0])
    for key in ("loss", "match_precision", "match_recall", "cls_precision", "cls_recall"):
        assert reported[key] == pytest.approx(recorded[key], rel=1e-6)
    val = train.validation_set(load_samples(str(data / "val.safetensors")), 0, 64)
    assert reported["keypoint_inlier_rate"] == pytest.approx(np.mean([(m >= 0).mean() for _, _, m in val]))
    assert 0.0 < reported["keypoint_inlier_rate"] < 1.0


def test_init_starts_a_new_run_from_an_export(data, tmp_path):
    first = tmp_path / "first"
    train.main(cli(data, first, "--epochs", "1"))
    start = exported(first / "last.safetensors")
    run = train.Run(train.parse_args(cli(data, tmp_path / "tuned", "--init", str(first / "last.safetensors"))))
    assert run.epoch == 0 and run.step == 0
    assert all(torch.equal(tensor, start[name]) for name, tensor in run.model.state_dict().items())
    wider = cli(data, tmp_path / "wider", "--init", str(first / "last.safetensors"), "--feature-dim", "48")
    with pytest.raises(SystemExit, match="differs from this run"):
        train.Run(train.parse_args(wider))


def test_validation_set_selects_a_scene_and_controls_the_outlier_rate():
    rng = np.random.default_rng(3)
    samples = [Sample(*random_sample(rng, 300, 60, 150), f"{scene}/q{i}/v0") for i, scene in enumerate("abab")]
    natural = train.validation_set(samples, 0, 1024)
    only_b = train.validation_set(samples, 0, 1024, scene="b")
    assert len(natural) == 4 and len(only_b) == 2
    assert all(np.array_equal(x[0], y[0]) for x, y in zip(only_b, natural[1::2])), "filtering changed the draw"
    for pts2d, pts3d, match in train.validation_set(samples, 0, 1024, outlier_rate=(0.5, 0.5)):
        inliers = int((match >= 0).sum())
        assert len(pts2d) - inliers == inliers and len(pts3d) - inliers == inliers
    assert any(len(p[0]) > 2 * int((p[2] >= 0).sum()) for p in natural), "no sample has more outliers than inliers"


def test_batched_forward_matches_the_per_sample_forward():
    """--batched training: one pass over equal-size samples gives each sample's plan, matches, loss and gradient."""
    torch.manual_seed(1)
    rng = np.random.default_rng(5)
    samples = [Sample(*random_sample(rng, 200, 90, 60), "s") for _ in range(3)]
    drawn = [train.subsample(s, np.random.default_rng(i), (0.5, 0.5), 64, 10) for i, s in enumerate(samples)]
    n2d, n3d = min(len(d[0]) for d in drawn), min(len(d[1]) for d in drawn)
    chunk = [train.crop(d, n2d, n3d) for d in drawn]
    model = GoMatch(ModelConfig(feature_dim=32, encoder_blocks=2, classifier_blocks=1))
    pts2d, pts3d, match = train.stacked_tensors(chunk, "cpu")

    batched = model.forward_batch(pts2d, pts3d)
    batched_outcomes = assess_batch(batched, match, 0.5)
    sum(o.loss for o in batched_outcomes).backward()
    batched_grads = [None if p.grad is None else p.grad.clone() for p in model.parameters()]
    model.zero_grad()
    singles = [model(pts2d[i], pts3d[i]) for i in range(len(chunk))]
    single_outcomes = [assess(r, m, 0.5) for r, m in zip(singles, match)]
    sum(o.loss for o in single_outcomes).backward()

    for i, s in enumerate(singles):
        valid = batched.valid[i]
        torch.testing.assert_close(batched.log_plan[i], s.log_plan, atol=1e-4, rtol=1e-4)
        assert torch.equal(batched.i3d[i][valid], s.i3d) and torch.equal(batched.i2d[i][valid], s.i2d)
        torch.testing.assert_close(batched.cls_logits[i][valid], s.cls_logits, atol=1e-4, rtol=1e-4)
    assert not batched.valid.all(), "no padding exercised"
    for b, s in zip(batched_outcomes, single_outcomes):
        torch.testing.assert_close(b.loss, s.loss, atol=1e-5, rtol=1e-5)
        assert (b.proposed, b.proposed_correct, b.gt_matches, b.kept) == (s.proposed, s.proposed_correct, s.gt_matches, s.kept)
    for g, p in zip(batched_grads, model.parameters()):
        if g is None:  # a bias in front of an InstanceNorm: no gradient in either pass
            assert p.grad is None
            continue
        torch.testing.assert_close(g, p.grad, atol=1e-4, rtol=1e-3)


def test_equal_size_batches_crop_to_the_smallest_sets_and_keep_the_matches():
    rng = np.random.default_rng(8)
    sizes = rng.integers([80, 40], [300, 80], size=(20, 2))
    samples = [Sample(*random_sample(rng, int(n3d), int(detected), 40), "s") for n3d, detected in sizes]
    prepared = [train.subsample(s, np.random.default_rng(i), (0.0, 1.0), 0, 10) for i, s in enumerate(samples)]
    batches = train.equal_size_batches(prepared, 4, np.random.default_rng(0))
    assert sorted(len(b) for b in batches) == [4] * 5
    originals = {p[0].tobytes()[:64]: p for p in prepared}
    for batch in batches:
        assert len({(len(p[0]), len(p[1])) for p in batch}) == 1, "sizes differ within a batch"
        for pts2d, pts3d, match in batch:
            full2d, full3d, full_match = originals[pts2d.tobytes()[:64]]
            assert np.array_equal(pts2d, full2d[: len(pts2d)]) and np.array_equal(pts3d, full3d[: len(pts3d)])
            kept = full_match[: len(pts2d)]
            assert np.array_equal(match, np.where(kept < len(pts3d), kept, -1))
    for part in (0, 1):
        assert sum(len(p[part]) for b in batches for p in b) < sum(len(p[part]) for p in prepared), "nothing cropped"
    again = train.equal_size_batches(prepared, 4, np.random.default_rng(0))
    assert all(np.array_equal(a[0], b[0]) for x, y in zip(batches, again) for a, b in zip(x, y))


def test_batched_cli_trains_and_resumes_exactly(data, tmp_path, capsys):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train.main(cli(data, straight, "--batched"))
    out = capsys.readouterr().out
    assert "epoch 1 validation: loss" in out and "% of their points kept by the equal-size crops" in out
    train.main(cli(data, resumed, "--batched", "--max-steps", "2"))
    train.main(cli(data, resumed, "--batched", "--resume"))
    a, b = exported(straight / "last.safetensors"), exported(resumed / "last.safetensors")
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed batched run diverged from the uninterrupted run"
    with pytest.raises(SystemExit, match="--batched"):
        train.main(cli(data, resumed, "--resume"))


def test_a_teacher_adds_the_distillation_loss_and_resumes_only_with_the_same_teacher(data, tmp_path, capsys):
    first = tmp_path / "first"
    train.main(cli(data, first, "--epochs", "1"))
    teacher = str(first / "last.safetensors")
    run = train.Run(train.parse_args(cli(data, tmp_path / "own", "--init", teacher, "--teacher", teacher)))
    outcome = run.assess_chunk([run_sample(data)])[0]
    assert abs(outcome.distill_loss.item()) < 1e-5, "a model distilling itself has nothing to learn"
    student = tmp_path / "student"
    train.main(cli(data, student, "--teacher", teacher, "--distill-weight", "2", "--epochs", "1"))
    assert "distil" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="options differ"):
        train.main(cli(data, student, "--resume", "--epochs", "2"))


def run_sample(data):
    """One training sample as the trainer prepares it."""
    sample = load_samples(str(data / "train.safetensors"))[0]
    return train.epoch_samples([sample], 0, train.parse_args(cli(data, "unused")))[0]
