"""Share of triangulated keypoints per block of stored keypoint order in a COLMAP model.

    python3 tools/train/keypoint_order.py ../shared/data/colmap/sceaux [--block 1024]

The evidence behind the protocol's keypoint caps (README "Protocol and `gomatch-sim eval`"): a
detector capped at N keypoints keeps its larger-scale features, and SIFT extractors list keypoints
octave by octave from fine to coarse, so larger-scale (more repeatable, more often triangulated)
keypoints come last. Prints, per image with more than one block, its keypoint count and the
triangulated share of each consecutive block, then the mean share of each image's first and last
block. Reads images.txt or images.bin; standard library only.
"""

import argparse
import struct
from pathlib import Path


def read_text_images(path: Path) -> dict[int, list[int]]:
    """Per image id, the 3D point id of each stored keypoint (-1: untriangulated)."""
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    images = {}
    for header, points in zip(lines[0::2], lines[1::2]):
        fields = points.split()
        images[int(header.split()[0])] = [int(v) for v in fields[2::3]]
    return images


def read_binary_images(path: Path) -> dict[int, list[int]]:
    """As read_text_images, from COLMAP's images.bin."""
    data = path.read_bytes()
    (count,), offset = struct.unpack_from("<Q", data), 8
    images = {}
    for _ in range(count):
        (image_id,) = struct.unpack_from("<I", data, offset)
        offset += 4 + 7 * 8 + 4  # id, qvec, tvec, camera id
        offset = data.index(b"\0", offset) + 1  # name
        (keypoints,) = struct.unpack_from("<Q", data, offset)
        offset += 8
        point_ids = struct.unpack_from("<" + "16xq" * keypoints, data, offset)  # skip x, y
        offset += 24 * keypoints
        images[image_id] = list(point_ids)
    return images


def read_images(model: Path) -> dict[int, list[int]]:
    text = model / "images.txt"
    return read_text_images(text) if text.exists() else read_binary_images(model / "images.bin")


def block_shares(point_ids: list[int], block: int) -> list[float]:
    """Triangulated share of each consecutive block of `block` keypoints (the last may be shorter)."""
    blocks = [point_ids[start : start + block] for start in range(0, len(point_ids), block)]
    return [sum(p != -1 for p in b) / len(b) for b in blocks]


def first_and_last_shares(images: dict[int, list[int]], block: int) -> list[tuple[int, float, float]]:
    """Per image with more than `block` keypoints: its id and the triangulated shares of its first and
    last `block` stored keypoints."""
    return [
        (image_id, block_shares(ids[:block], block)[0], block_shares(ids[-block:], block)[0])
        for image_id, ids in sorted(images.items())
        if len(ids) > block
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="COLMAP model directory (images.txt or images.bin)")
    parser.add_argument("--block", type=int, default=1024, help="keypoints per block (the protocol's cap)")
    args = parser.parse_args()
    images = read_images(args.model)
    capped = first_and_last_shares(images, args.block)
    for image_id, _, _ in capped:
        shares = " ".join(f"{s:.2f}" for s in block_shares(images[image_id], args.block))
        print(f"image {image_id}: {len(images[image_id])} keypoints, blocks {shares}")
    if not capped:
        print(f"no image has more than {args.block} keypoints")
        return
    first = sum(f for _, f, _ in capped) / len(capped)
    last = sum(last for _, _, last in capped) / len(capped)
    print(
        f"{len(capped)} images: triangulated share of the first {args.block} keypoints {first:.3f}, "
        f"of the last {args.block} {last:.3f}"
    )


if __name__ == "__main__":
    main()
