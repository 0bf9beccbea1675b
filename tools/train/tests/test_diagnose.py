"""The failure diagnosis: viewpoint change, rotated views, and tables that pool as the trainer's validation does."""

import json

import numpy as np
import pytest

from gomatch_train import diagnose, train, validate
from gomatch_train.dataset import Sample
from gomatch_train.synthetic import random_sample

TINY = ["--feature-dim", "32", "--encoder-blocks", "2", "--classifier-blocks", "1"]


def identical_views(rng):
    pts2d, pts3d, match = random_sample(rng, 120, 80, 40)
    pts3d = pts3d.copy()
    pts3d[match[match >= 0]] = pts2d[match >= 0]  # each matched 3D point seen where its keypoint lies
    return Sample(pts2d, pts3d, match, "collection/3/q1/v2")


def test_viewpoint_change_is_zero_for_the_same_bearings_and_at_most_the_turn_after_a_rotation():
    rng = np.random.default_rng(0)
    sample = identical_views(rng)
    assert diagnose.viewpoint_change(sample) == pytest.approx(0.0, abs=1e-3)
    turned = diagnose.rotated_view(sample, 30.0, rng)
    assert 0.0 < diagnose.viewpoint_change(turned) <= 30.0 + 1e-3
    unmatched = Sample(sample.pts2d, sample.pts3d, np.full(len(sample.pts2d), -1), "x/q/v")
    assert np.isnan(diagnose.viewpoint_change(unmatched))


def test_a_rotated_view_drops_the_points_behind_it_and_keeps_the_other_matches():
    rng = np.random.default_rng(1)
    sample = identical_views(rng)
    turned = diagnose.rotated_view(sample, 120.0, rng)
    assert len(turned.pts3d) < len(sample.pts3d)
    valid = turned.match >= 0
    assert np.all(turned.match[valid] < len(turned.pts3d))
    # A match survives exactly when its point is still in front of the turned camera.
    assert valid.sum() <= (sample.match >= 0).sum()
    assert sample.name == turned.name and turned.pts2d is sample.pts2d


def test_scene_groups_pool_synthetic_scenes_by_kind():
    assert diagnose.scene_group("colmap/mouse/q3/v7") == "colmap/mouse"
    assert diagnose.scene_group("collection/12/q0/v1") == "collection"


def test_tables_pool_every_sample_as_validate_does(data, tmp_path, capsys):
    out = tmp_path / "run"
    train.main(["--train", str(data / "train.safetensors"), "--val", str(data / "val.safetensors"), "--out", str(out),
                "--epochs", "1", "--batch", "2", "--max-points", "64", "--min-points", "20", *TINY])  # fmt: skip
    capsys.readouterr()
    validate.main([str(out / "best.safetensors"), str(data / "val.safetensors"), "--max-points", "64"])
    reported = json.loads(capsys.readouterr().out)
    diagnose.main([str(out / "best.safetensors"), str(data / "val.safetensors"), "--max-points", "64",
                   "--rates", "0.5", "--threads", "1"])  # fmt: skip
    angles, rates = capsys.readouterr().out.strip().split("\n\n")
    pooled = f"{reported['match_precision']:.3f} / {reported['match_recall']:.3f}"
    assert angles.splitlines()[-1].startswith(f"| all | {reported['samples']} |")
    assert angles.splitlines()[-1].endswith(f"| {pooled} |")
    assert "outlier rate 0.5" in rates.splitlines()[0]
    assert rates.splitlines()[-1].startswith(f"| all | {reported['samples']} | ")
    assert rates.splitlines()[-1].split(" | ")[4] == pooled
