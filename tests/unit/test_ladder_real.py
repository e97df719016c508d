"""The ladder on the six real nuScenes frames: damage grows strictly from S1 to S5, and every cell is
bit-identical across processes."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from pytest_drivedegrade import FAMILIES, corrupt, corrupt_sample
from pytest_drivedegrade.constants import CAMERAS

GRADED = [n for n, f in FAMILIES.items() if f.scope == "image" and n != "occlusion"]


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    d = a.astype(np.float64) - b
    return float((d * d).mean())


@pytest.mark.parametrize("family", GRADED)
def test_damage_strictly_increases_along_the_ladder(family, nuscenes_frames):
    """Mean squared error against clean over the six real frames (i.e. PSNR falls) at S1 < ... < S5.

    A random family's realisation (a blur direction, where the drops fall) differs per severity, so its
    damage is averaged over three realisations per frame."""
    keys = ("real-a", "real-b", "real-c") if FAMILIES[family].random else ("real",)
    damage = []
    for severity in range(1, 6):
        damage.append(np.mean([_mse(corrupt(img, family, severity, frame=key, camera=cam), img)
                               for cam, (_, img) in nuscenes_frames.items() for key in keys]))
    assert all(a < b for a, b in zip(damage, damage[1:])), dict(zip(range(1, 6), damage))


def test_removed_fraction_strictly_increases_for_occlusion(nuscenes_frames):
    removed = []
    for severity in range(1, 6):
        removed.append(np.mean([(corrupt(img, "occlusion", severity, frame="real", camera=cam) != img)
                                .any(axis=2).mean() for cam, (_, img) in nuscenes_frames.items()]))
    assert all(a < b for a, b in zip(removed, removed[1:])), removed


def test_removed_fraction_strictly_increases_for_frame_dropout(nuscenes_frames):
    images = {cam: img for cam, (_, img) in nuscenes_frames.items()}
    small = {cam: img[::16, ::16].copy() for cam, img in images.items()}
    removed = []
    for severity in range(1, 6):
        lost = [not out.any() for k in range(40)
                for out in corrupt_sample(small, "frame_dropout", severity, frame=f"k{k}").values()]
        removed.append(np.mean(lost))
    assert all(a < b for a, b in zip(removed, removed[1:])), removed


_CHILD = """
import hashlib, json, sys
import numpy as np
from pytest_drivedegrade import corrupt_sample
from pytest_drivedegrade.corruptions.preview import camera_of, read_rgb
paths, cells = json.loads(sys.argv[1]), json.loads(sys.argv[2])
images = {camera_of(p): read_rgb(p)[::4, ::4].copy() for p in paths}
out = {}
for family, severity in cells:
    sample = corrupt_sample(images, family, severity, seed=7, frame="tok")
    out[f"{family}-s{severity}"] = hashlib.sha256(b"".join(sample[c].tobytes() for c in sorted(sample))).hexdigest()
print(json.dumps(out))
"""


def test_cells_are_bit_identical_across_processes(nuscenes_frames):
    paths = [str(p) for p, _ in nuscenes_frames.values()]
    cells = [[name, s] for name in FAMILIES for s in (2, 5)]
    # two fresh interpreters, the second computing the cells in reverse order
    runs = [json.loads(subprocess.run([sys.executable, "-c", _CHILD, json.dumps(paths), json.dumps(c)],
                                      check=True, capture_output=True, text=True).stdout)
            for c in (cells, cells[::-1])]
    assert runs[0] == runs[1]
    s5 = [h for cell, h in runs[0].items() if cell.endswith("-s5")]
    assert len(set(s5)) == len(s5)  # every S5 cell is a different image set
    images = {cam: img[::4, ::4].copy() for cam, (_, img) in nuscenes_frames.items()}
    sample = corrupt_sample(images, "snow", 5, seed=7, frame="tok")
    here = hashlib.sha256(b"".join(sample[c].tobytes() for c in sorted(sample))).hexdigest()
    assert here == runs[0]["snow-s5"]
    assert set(images) == set(CAMERAS)
