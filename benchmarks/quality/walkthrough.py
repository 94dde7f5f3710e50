"""Lay a walk-through folder (images/, depth/, poses.txt, K.txt; e.g. shared/data/hololens-office)
out as a 7-Scenes scene, so that `reloc ingest` takes its ground truth along for evaluation.

The split is by time: the first frames train (seq-01), the last ``--test`` frames test (seq-02);
the test frames are later along the same walk, so they are near, but not on, the training path.

    python benchmarks/quality/walkthrough.py ../shared/data/hololens-office /tmp/holo-scene --test 30
    reloc ingest /tmp/holo-scene -o /tmp/holo-shards
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import yaml


def lay_out(src: Path, out: Path, test: int) -> dict[str, int]:
    """Write ``out`` (seq-01 train, seq-02 test, split files, intrinsics.yaml); returns frame counts."""
    import cv2

    images = sorted((src / "images").glob("*.png"))
    depths = sorted((src / "depth").glob("*.png"))
    poses = np.loadtxt(src / "poses.txt").reshape(-1, 4, 4)
    K = np.loadtxt(src / "K.txt").reshape(3, 3)
    if not (len(images) == len(depths) == len(poses)) or not 0 < test < len(images):
        raise SystemExit(f"{src}: {len(images)} images, {len(depths)} depth maps, {len(poses)} poses; "
                         f"--test must be in 1..{len(images) - 1}")
    h, w = cv2.imread(str(images[0])).shape[:2]
    out.mkdir(parents=True, exist_ok=False)
    n_train = len(images) - test
    for seq, lo, hi in (("seq-01", 0, n_train), ("seq-02", n_train, len(images))):
        d = out / seq
        d.mkdir()
        for j, i in enumerate(range(lo, hi)):
            stem = d / f"frame-{j:06d}"
            shutil.copyfile(images[i], f"{stem}.color.png")
            shutil.copyfile(depths[i], f"{stem}.depth.png")
            np.savetxt(f"{stem}.pose.txt", poses[i], delimiter="\t", fmt="%.8f")
    (out / "TrainSplit.txt").write_text("sequence1\n")
    (out / "TestSplit.txt").write_text("sequence2\n")
    (out / "intrinsics.yaml").write_text(yaml.safe_dump({
        "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "width": int(w), "height": int(h)}))
    return {"train": n_train, "test": test}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path, help="walk-through folder: images/, depth/, poses.txt, K.txt")
    ap.add_argument("out", type=Path, help="new 7-Scenes-layout folder")
    ap.add_argument("--test", type=int, default=30, help="last N frames form the test sequence")
    args = ap.parse_args()
    print(lay_out(args.src, args.out, args.test))


if __name__ == "__main__":
    main()
