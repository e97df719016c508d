"""Injector throughput: median milliseconds per 1600x900 image, per family at S3 and S5, on one thread.

Prints each family beside the memory-copy floor measured in the same run and, where `imagecorruptions`
is importable, the ratio against its nearest corruption. Run by hand:

    OMP_NUM_THREADS=1 python benchmarks/injector.py [--repeats 11] [--passes 3] [--image PATH] [--family F]
        [--all-severities]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from pytest_drivedegrade import FAMILIES  # noqa: E402
from pytest_drivedegrade.corruptions.preview import read_rgb, render  # noqa: E402

DEFAULT_IMAGE = next((Path(__file__).resolve().parents[1] / "tests" / "data" / "nuscenes").glob("*__CAM_FRONT__*.jpg"))
#: our family -> imagecorruptions' nearest corruption
NEAREST = {"gaussian_noise": "gaussian_noise", "gaussian_blur": "gaussian_blur", "motion_blur": "motion_blur",
           "jpeg": "jpeg_compression", "fog": "fog", "snow": "snow", "downscale": "pixelate"}


#: The clock: CPU time of this thread (one thread does all the work), which a process waiting for a core on a
#: shared machine does not accumulate; --clock wall uses the wall clock instead.
CLOCK = time.thread_time


def median_ms(fn, repeats: int) -> float:
    fn()  # warm caches and lazy tables once
    times = []
    for _ in range(repeats):
        start = CLOCK()
        fn()
        times.append(CLOCK() - start)
    return statistics.median(times) * 1000


def ours(image: np.ndarray, family: str, severity: int, counter: list[int]):
    def run():
        counter[0] += 1  # a new realisation each call, as in a run over frames
        return render(image, family, severity, seed=0, frame=str(counter[0]), camera="CAM_FRONT")
    return run


def _skimage_shim() -> None:
    """imagecorruptions 1.1.2 calls skimage's gaussian(..., multichannel=True), which scikit-image 0.19 renamed
    to channel_axis, and numpy's float_, which numpy 2 removed; map both so the reference runs in the same
    process as ours on the project's own numpy and OpenCV."""
    import inspect

    if not hasattr(np, "float_"):
        np.float_ = np.float64

    import skimage.filters

    original = skimage.filters.gaussian
    if "multichannel" in inspect.signature(original).parameters:
        return

    def gaussian(image, *args, multichannel=None, **kwargs):
        if multichannel:
            kwargs.setdefault("channel_axis", -1)
        return original(image, *args, **kwargs)

    skimage.filters.gaussian = gaussian


def reference(image: np.ndarray, family: str, severity: int):
    try:
        _skimage_shim()
        import imagecorruptions.corruptions as ic_module
        from imagecorruptions import corrupt as ic_corrupt
    except ImportError:
        return None
    ic_module.gaussian = __import__("skimage.filters", fromlist=["gaussian"]).gaussian
    name = NEAREST.get(family)
    return None if name is None else (lambda: ic_corrupt(image, corruption_name=name, severity=severity))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=11, help="timed calls per family and severity in a pass")
    parser.add_argument("--passes", type=int, default=3,
                        help="sequential passes over all families; each figure is its best pass's median, so "
                             "a transient slow phase of the shared machine does not land on one family")
    parser.add_argument("--image", default=str(DEFAULT_IMAGE))
    parser.add_argument("--no-reference", action="store_true", help="skip imagecorruptions even if present")
    parser.add_argument("--clock", choices=("cpu", "wall"), default="cpu")
    parser.add_argument("--family", action="append", choices=list(FAMILIES),
                        help="time only this family (repeatable); the S5 sum then covers only these")
    parser.add_argument("--all-severities", action="store_true",
                        help="also time S1, S2 and S4 and print the slowest of the five (the 25 ms target is "
                             "per severity)")
    args = parser.parse_args()
    global CLOCK
    CLOCK = time.thread_time if args.clock == "cpu" else time.perf_counter
    cv2.setNumThreads(1)
    image = read_rgb(args.image)
    floor = median_ms(image.copy, args.repeats * 4)
    print(f"image {image.shape[1]}x{image.shape[0]}, one thread, {args.clock} time, median of {args.repeats} calls, "
          f"best of {args.passes} passes; copy floor {floor:.3f} ms")
    severities = (1, 2, 3, 4, 5) if args.all_severities else (3, 5)
    worst_head = f" {'max S1-5':>9s}" if args.all_severities else ""
    print(f"{'family':15s} {'S3 ms':>8s} {'S5 ms':>8s}{worst_head} {'S5/copy':>8s} {'ref S3':>8s} {'ref S5':>8s} "
          f"{'x faster':>9s}")
    families = args.family or list(FAMILIES)
    counter = [0]
    # all of ours first, then the references: imagecorruptions' large float64 temporaries would otherwise
    # leave the allocator in a state where our next image-sized arrays page-fault afresh
    mine = {f: {s: float("inf") for s in severities} for f in families}
    for _ in range(args.passes):
        for f in families:
            for s in severities:
                mine[f][s] = min(mine[f][s], median_ms(ours(image, f, s, counter), args.repeats))
    refs = {}
    for family in families:  # the same statistic for the reference: best pass of a median
        ref = [None if args.no_reference else reference(image, family, s) for s in (3, 5)]
        refs[family] = [min(median_ms(r, 3) for _ in range(args.passes)) if r else None for r in ref]
    total_s5 = 0.0
    for family in families:
        s3, s5 = mine[family][3], mine[family][5]
        r3, r5 = refs[family]
        worst = f" {max(mine[family].values()):9.2f}" if args.all_severities else ""
        total_s5 += s5
        ratio = f"{min(r3 / s3, r5 / s5):9.1f}" if r3 and r5 else f"{'-':>9s}"
        fmt = lambda v: f"{v:8.1f}" if v is not None else f"{'-':>8s}"  # noqa: E731
        print(f"{family:15s} {s3:8.2f} {s5:8.2f}{worst} {s5 / floor:8.1f} {fmt(r3)} {fmt(r5)} {ratio}")
    label = "sixteen families" if not args.family else f"{len(args.family)} families"
    print(f"{label} at S5 together: {total_s5:.1f} ms")
    if "jpeg" in families:
        # the codec's own floor: libjpeg-turbo encode + decode of the same image at S3's quality, no colour swaps
        quality = [cv2.IMWRITE_JPEG_QUALITY, int(FAMILIES["jpeg"].value(3))]
        codec = median_ms(lambda: cv2.imdecode(cv2.imencode(".jpg", image, quality)[1], cv2.IMREAD_COLOR),
                          args.repeats)
        print(f"jpeg S3 {mine['jpeg'][3]:.2f} ms against the bare codec round trip {codec:.2f} ms "
              f"({mine['jpeg'][3] / codec:.2f}x): no faithful JPEG family can be much faster than its codec")


if __name__ == "__main__":
    main()
