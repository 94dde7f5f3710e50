"""Lay a walk-through folder (images/, depth/, poses.txt, K.txt; e.g. shared/data/hololens-office)
out as a 7-Scenes scene, so that `reloc ingest` takes its ground truth along for evaluation.

The split is by time. By default the first frames train (seq-01) and the last ``--test`` frames
test (seq-02): the test frames are later along the same walk, beyond every training frame, so
depth and pose must extrapolate to parts of the place never trained on. With ``--blocks B`` the
test frames are B blocks spread evenly inside the walk, each between training frames (train and
test sequences alternate: seq-01 train, seq-02 test, ...), the way 7-Scenes' test sequences
revisit the places its training sequences saw. With ``--every N`` every Nth frame (from the
second) is a test frame: one training sequence and one test sequence, both along the whole walk,
each test frame between two training ones. Only this layout has every test place seen by training
frames: the blocks' training stretches of a walk barely see each other (on hololens-office no two
of their links agree, with the true poses and depth too; README, Quality).

    python benchmarks/quality/walkthrough.py ../shared/data/hololens-office /tmp/holo-scene --test 30
    python benchmarks/quality/walkthrough.py ../shared/data/hololens-office /tmp/holo-inside --blocks 3
    python benchmarks/quality/walkthrough.py ../shared/data/hololens-office /tmp/holo-every --every 2
    reloc ingest /tmp/holo-scene -o /tmp/holo-shards
"""

from __future__ import annotations

import argparse
import itertools
import shutil
from pathlib import Path

import numpy as np
import yaml


def test_ranges(n: int, test: int, blocks: int = 1) -> list[tuple[int, int]]:
    """Frame ranges ``[lo, hi)`` of the test frames among ``n``: the last ``test`` (``blocks`` 1), or
    ``blocks`` near-equal blocks centred at (i + 1/2) / blocks of the walk, with training frames
    before, between and after them."""
    if not 1 <= blocks <= test or not 0 < test < n:
        raise SystemExit(f"the test frames must number 1..{n - 1} and the blocks 1..that many (got {test} "
                         f"frames in {blocks} blocks)")
    if blocks == 1:
        return [(n - test, n)]
    ranges = []
    for i in range(blocks):
        size = test // blocks + (i < test % blocks)
        lo = round((i + 0.5) * n / blocks) - size // 2
        ranges.append((lo, lo + size))
    bounds = [0, *[x for r in ranges for x in r], n]
    if any(b <= a for a, b in zip(bounds[::2], bounds[1::2])):  # a training stretch would be empty
        raise SystemExit(f"{test} test frames in {blocks} blocks leave no training frames between "
                         f"them in a walk of {n}: use fewer or smaller blocks")
    return ranges


def interleaved(n: int, every: int) -> tuple[list[int], list[int]]:
    """Frame indices (train, test) of ``n`` with every ``every``-th frame, from the second, a test
    frame: each test frame has training frames on both sides (the last one too, when it is not
    the walk's last frame)."""
    if every < 2 or n < 2 * every:
        raise SystemExit(f"--every must be >= 2 and leave two test frames in a walk of {n} (got {every})")
    test = list(range(1, n, every))
    return [i for i in range(n) if i % every != 1], test


def lay_out(src: Path, out: Path, test: int, blocks: int = 1, every: int = 0) -> dict[str, int]:
    """Write ``out`` (sequences in time order, train and test; split files, intrinsics.yaml);
    returns frame and sequence counts. ``every`` > 0: one interleaved training and test sequence
    (:func:`interleaved`; ``test`` and ``blocks`` unused)."""
    import cv2

    images = sorted((src / "images").glob("*.png"))
    depths = sorted((src / "depth").glob("*.png"))
    poses = np.loadtxt(src / "poses.txt").reshape(-1, 4, 4)
    K = np.loadtxt(src / "K.txt").reshape(3, 3)
    if not (len(images) == len(depths) == len(poses)):
        raise SystemExit(f"{src}: {len(images)} images, {len(depths)} depth maps, {len(poses)} poses")
    n = len(images)
    if every:
        sequences = list(zip(interleaved(n, every), (False, True)))
    else:
        tests = test_ranges(n, test, blocks)
        cuts = sorted({0, n, *[x for r in tests for x in r]})
        sequences = [(list(range(lo, hi)), (lo, hi) in tests) for lo, hi in itertools.pairwise(cuts)]
    h, w = cv2.imread(str(images[0])).shape[:2]
    out.mkdir(parents=True, exist_ok=False)
    split: dict[str, list[str]] = {"train": [], "test": []}
    for number, (frames, is_test) in enumerate(sequences, start=1):
        d = out / f"seq-{number:02d}"
        d.mkdir()
        split["test" if is_test else "train"].append(f"sequence{number}")
        for j, i in enumerate(frames):
            stem = d / f"frame-{j:06d}"
            shutil.copyfile(images[i], f"{stem}.color.png")
            shutil.copyfile(depths[i], f"{stem}.depth.png")
            np.savetxt(f"{stem}.pose.txt", poses[i], delimiter="\t", fmt="%.8f")
    (out / "TrainSplit.txt").write_text("".join(f"{x}\n" for x in split["train"]))
    (out / "TestSplit.txt").write_text("".join(f"{x}\n" for x in split["test"]))
    (out / "intrinsics.yaml").write_text(yaml.safe_dump({
        "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "width": int(w), "height": int(h)}))
    n_test = sum(len(f) for f, is_test in sequences if is_test)
    return {"train": n - n_test, "test": n_test, "train_sequences": len(split["train"]),
            "test_sequences": len(split["test"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path, help="walk-through folder: images/, depth/, poses.txt, K.txt")
    ap.add_argument("out", type=Path, help="new 7-Scenes-layout folder")
    ap.add_argument("--test", type=int, default=30, help="number of test frames (default: the last 30)")
    ap.add_argument("--blocks", type=int, default=1,
                    help="test frames in B blocks spread inside the walk (default 1: the walk's end)")
    ap.add_argument("--every", type=int, default=0,
                    help="every Nth frame (from the second) a test frame: one training and one test sequence "
                         "along the whole walk (--test and --blocks unused)")
    args = ap.parse_args()
    print(lay_out(args.src, args.out, args.test, args.blocks, args.every))


if __name__ == "__main__":
    main()
