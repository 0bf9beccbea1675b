"""keypoint_order.py: both COLMAP readers, and the measured trend on sceaux behind the protocol's caps."""

import subprocess
import sys

from conftest import REPO_ROOT, SHARED, require

sys.path.insert(0, str(REPO_ROOT / "tools" / "train"))
import keypoint_order  # noqa: E402

SCRIPT = REPO_ROOT / "tools" / "train" / "keypoint_order.py"


def test_block_shares_count_triangulated_keypoints_per_block():
    assert keypoint_order.block_shares([-1, 3, 4, -1, 7], 2) == [0.5, 0.5, 1.0]


def test_text_and_binary_models_are_read():
    sceaux, mouse = SHARED / "data/colmap/sceaux", SHARED / "data/colmap/mouse"
    require(sceaux)
    text = keypoint_order.read_images(sceaux)
    assert len(text) == 11 and all(len(ids) > 9000 for ids in text.values())
    binary = keypoint_order.read_images(mouse)
    assert len(binary) == 56
    triangulated = sum(p != -1 for ids in binary.values() for p in ids)
    total = sum(len(ids) for ids in binary.values())
    assert 0.40 < triangulated / total < 0.55  # data README: 47 % triangulated


def test_sceaux_keypoints_stored_last_are_triangulated_more_often():
    sceaux = SHARED / "data/colmap/sceaux"
    require(sceaux)
    shares = keypoint_order.first_and_last_shares(keypoint_order.read_images(sceaux), 1024)
    assert len(shares) == 11
    first = sum(f for _, f, _ in shares) / len(shares)
    last = sum(last for _, _, last in shares) / len(shares)
    assert last > first + 0.15, (first, last)
    out = subprocess.run([sys.executable, str(SCRIPT), str(sceaux)], check=True, capture_output=True, text=True)
    assert out.stdout.splitlines()[-1].startswith("11 images: triangulated share of the first 1024 keypoints")
