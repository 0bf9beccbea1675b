"""Dataset reading and the per-epoch subsampling (outlier-rate control, point budget, permutation)."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from gomatch_train.dataset import Sample, load_samples, point_counts, subsample
from gomatch_train.synthetic import mutual_matches, random_sample, write_dataset


@pytest.mark.parametrize(
    "counts, rate, budget, minimum, expected",
    [
        ((100, 300, 50), (0.5, 0.5), 0, 0, (50, 50, 50)),  # too few 3D outliers: inliers cut to reach rate 0.5
        ((100, 300, 200), (0.5, 0.5), 0, 0, (100, 100, 100)),  # outliers capped at rate 0.5
        ((200, 200, 200), (0.5, 0.5), 256, 100, (128, 128, 128)),  # scaled to the budget
        ((40, 40, 40), (0.5, 0.5), 256, 100, None),  # smaller set below the minimum
        ((100, 300, 50), (0.0, 1.0), 256, 10, (64, 192, 32)),  # no outlier control, budget only
        ((100, 300, 50), (0.0, 0.5), 0, 0, (100, 100, 50)),  # cap only
    ],
)
def test_point_counts(counts, rate, budget, minimum, expected):
    assert point_counts(*counts, rate, budget, minimum) == expected


def synthetic_sample(seed=0) -> Sample:
    pts2d, pts3d, match = random_sample(np.random.default_rng(seed), 500, 300, 150)
    return Sample(pts2d, pts3d, match, "synthetic")


def test_subsample_keeps_gt_pairs_and_permutes():
    sample = synthetic_sample()
    pts2d, pts3d, match = subsample(sample, np.random.default_rng(1), (0.5, 0.5), 256, 100)
    n_in = int((match >= 0).sum())
    assert max(len(pts2d), len(pts3d)) <= 256
    assert len(pts2d) - n_in == n_in and len(pts3d) - n_in == n_in  # outlier rate exactly 0.5 in both sets
    assert len(np.unique(match[match >= 0])) == n_in

    # Every kept keypoint and 3D point is an original one, and kept GT pairs are original GT pairs.
    index2d = {p.tobytes(): i for i, p in enumerate(sample.pts2d)}
    index3d = {p.tobytes(): i for i, p in enumerate(sample.pts3d)}
    orig2d = np.array([index2d[p.tobytes()] for p in pts2d])
    orig3d = np.array([index3d[p.tobytes()] for p in pts3d])
    expected = np.where(match >= 0, orig3d[np.maximum(match, 0)], -1)
    np.testing.assert_array_equal(sample.match[orig2d], expected)
    assert not np.all(np.diff(orig2d) > 0), "2D points were not permuted"


def test_subsample_is_a_function_of_the_generator_seed():
    sample = synthetic_sample()
    a = subsample(sample, np.random.default_rng(7), (0.5, 0.5), 128, 10)
    b = subsample(sample, np.random.default_rng(7), (0.5, 0.5), 128, 10)
    c = subsample(sample, np.random.default_rng(8), (0.5, 0.5), 128, 10)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])


def test_dataset_file_round_trip(tmp_path):
    samples = [random_sample(np.random.default_rng(s), 200, 120, 40) for s in range(3)]
    path = tmp_path / "d.safetensors"
    write_dataset(str(path), samples, scene="synthetic/0042")
    loaded = load_samples(str(path))
    assert len(loaded) == 3
    for (pts2d, pts3d, match), got in zip(samples, loaded):
        np.testing.assert_array_equal(got.pts2d, pts2d)
        np.testing.assert_array_equal(got.pts3d, pts3d)
        np.testing.assert_array_equal(got.match, match)
    assert loaded[1].name == "synthetic/0042/q1/v1001"


def test_synthetic_ground_truth_is_mutual_nearest_within_threshold():
    keypoints = np.array([[0.0, 0.0], [0.1, 0.0], [0.3, 0.3], [0.5, 0.5]])
    projections = np.array([[0.0, 0.0004], [0.1004, 0.0], [0.1006, 0.0], [0.3, 0.302], [0.5, 0.5]])
    valid = np.array([True, True, True, True, False])
    # kp1's nearest is projection 1 (mutual); projection 3 is too far; projection 4 is not valid (behind camera).
    np.testing.assert_array_equal(mutual_matches(keypoints, projections, valid), [0, 1, -1, -1])


def write_raw(path, tensors, metadata):
    save_file({k: torch.from_numpy(v) for k, v in tensors.items()}, str(path), metadata=metadata)


def minimal_tensors(match):
    return {
        "pts2d": np.zeros((len(match), 2), np.float32),
        "pts3d": np.zeros((3, 2), np.float32),
        "match": np.array(match, np.int64),
        "offsets2d": np.array([0, len(match)], np.int64),
        "offsets3d": np.array([0, 3], np.int64),
        "scene": np.zeros(1, np.int64),
        "query": np.zeros(1, np.int64),
        "view": np.zeros(1, np.int64),
    }


def test_load_rejects_other_formats_and_bad_matches(tmp_path):
    good_meta = {"format": "gomatch-dataset", "version": "1", "scenes": json.dumps(["s"]), "protocol": "{}"}
    path = tmp_path / "x.safetensors"
    write_raw(path, minimal_tensors([0, -1]), {**good_meta, "version": "2"})
    with pytest.raises(ValueError, match="not a gomatch-dataset v1"):
        load_samples(str(path))
    write_raw(path, minimal_tensors([0, 3]), good_meta)
    with pytest.raises(ValueError, match="outside"):
        load_samples(str(path))
    write_raw(path, minimal_tensors([1, 1]), good_meta)
    with pytest.raises(ValueError, match="several keypoints"):
        load_samples(str(path))
