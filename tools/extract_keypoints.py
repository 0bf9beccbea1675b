#!/usr/bin/env python3
"""SIFT keypoints of photos, detected anew, in a COLMAP database: what `colmap feature_extractor` writes.

    python3 tools/extract_keypoints.py DATABASE IMAGE_DIR [NAME ...]

Runs pycolmap's `extract_features` (COLMAP's SIFT on the CPU, its default options: at most 8,192 features per
image) on the named images of IMAGE_DIR (all of them without names) and writes DATABASE, which
`gomatch-sim localize --database DATABASE` reads (keypoints ranked largest scale first). Needs pycolmap
(tools/train/requirements.txt; `tools/train/setup_venv.sh` prints the venv holding it). Prints per image the
number of keypoints.
"""
import sqlite3
import sys
from pathlib import Path

import pycolmap


def main() -> None:
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    database, images, names = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:]
    database.unlink(missing_ok=True)
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = 1  # the same keypoints on every machine
    pycolmap.extract_features(database, images, image_names=names, extraction_options=options,
                              device=pycolmap.Device.cpu)
    with sqlite3.connect(database) as db:
        rows = db.execute("SELECT images.name, keypoints.rows FROM images JOIN keypoints USING (image_id)")
        for name, count in sorted(rows):
            print(f"{name}: {count} keypoints")


if __name__ == "__main__":
    main()
