"""`drivedegrade preview`: one image under every family at one severity (the paper's Figure 2A), or one
family across S1..S5, as a labelled PNG montage."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..atomic import atomic_write_bytes
from ..errors import InvalidInput
from .api import check_family, check_severity, corrupt, corrupt_sample
from .hooks import camera_of
from .ladder import FAMILIES


def read_rgb(path: str | Path) -> np.ndarray:
    """Decode an image file to H x W x 3 uint8 RGB, or InvalidInput naming the file."""
    data = np.fromfile(str(path), dtype=np.uint8) if Path(path).is_file() else None
    if data is None:
        raise InvalidInput(f"{path}: no such image file")
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if bgr is None:
        raise InvalidInput(f"{path}: not a readable image (truncated or not JPEG/PNG)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def render(image: np.ndarray, family: str, severity: int, *, seed: int, frame: str, camera: str) -> np.ndarray:
    """One family on one image; stream families go through the sample API with this camera alone."""
    if FAMILIES[family].scope == "image":
        return corrupt(image, family, severity, seed=seed, frame=frame, camera=camera)
    return corrupt_sample({camera: image}, family, severity, seed=seed, frame=frame)[camera]


_FONT = cv2.FONT_HERSHEY_SIMPLEX
_LINE_PX = 18  # height of one label line
_MARGIN_PX = 6


def _fit_scale(text: str, width: int, largest: float = 0.45) -> float:
    """The largest font scale (at most `largest`) at which `text` fits in `width` minus the margins."""
    room = max(1, width - 2 * _MARGIN_PX)
    scale = largest
    while scale > 0.1 and cv2.getTextSize(text, _FONT, scale, 1)[0][0] > room:  # glyph widths round: not linear
        scale *= 0.95
    return scale


def _tile(image: np.ndarray, label: str, width: int) -> np.ndarray:
    """The image resized to `width` under a label bar: "family S4" on the first line and the parameter on the
    second, each scaled down to fit the tile (a long label never runs into the next tile)."""
    h = round(image.shape[0] * width / image.shape[1])
    tile = cv2.resize(image, (width, h), interpolation=cv2.INTER_AREA)
    lines = [part.strip() for part in label.split(":", 1)]
    bar = np.full((_LINE_PX * 2 + 6, width, 3), 20, np.uint8)  # two lines for every tile, so rows align
    for i, text in enumerate(lines):
        cv2.putText(bar, text, (_MARGIN_PX, _LINE_PX * (i + 1) - 4), _FONT, _fit_scale(text, width),
                    (235, 235, 235), 1, cv2.LINE_AA)
    return np.vstack([bar, tile])


def _grid(tiles: list[np.ndarray], columns: int, note: str = "") -> np.ndarray:
    """`tiles` in rows of `columns`; a row's empty places are grey tiles labelled `note` (a black one read as a
    blacked-out camera without a label)."""
    blank = np.full_like(tiles[0], 128)
    if note:
        blank = _tile(np.full((8, 8, 3), 128, np.uint8), note, tiles[0].shape[1])[:tiles[0].shape[0]]
    rows = [tiles[i:i + columns] + [blank] * (columns - len(tiles[i:i + columns]))
            for i in range(0, len(tiles), columns)]
    return np.vstack([np.hstack(r) for r in rows])


def montage(image: np.ndarray, *, severity: int | None = None, family: str | None = None, seed: int = 0,
            frame: str = "", camera: str = "CAM_FRONT", width: int = 480) -> np.ndarray:
    """All sixteen families at `severity` (with the clean image first), or `family` at S1..S5."""
    tiles = [_tile(image, "clean", width)]
    if family is not None:
        fam = FAMILIES[check_family(family)]
        for s in range(1, 6):
            out = render(image, family, s, seed=seed, frame=frame, camera=camera)
            tiles.append(_tile(out, f"{family} S{s}: {fam.describe(s)}", width))
        return _grid(tiles, 3)
    severity = check_severity(severity if severity is not None else 4)
    for name, fam in FAMILIES.items():
        out = render(image, name, severity, seed=seed, frame=frame, camera=camera)
        tiles.append(_tile(out, f"{name} S{severity}: {fam.describe(severity)}", width))
    return _grid(tiles, 6, note=f"this montage: {len(FAMILIES)} families at S{severity}, clean first")


def write_preview(images: Sequence[str], *, severity: int = 4, family: str | None = None,
                  out: str = "montage.png", seed: int = 0, width: int = 480) -> Path:
    """Render the montage of each image (stacked vertically) into one PNG; returns its path."""
    if width < 64:
        raise InvalidInput(f"--width must be at least 64 pixels, got {width}")
    panels = []
    for path in images:
        rgb = read_rgb(path)
        panels.append(montage(rgb, severity=severity, family=family, seed=seed, frame=Path(path).stem,
                              camera=camera_of(path), width=width))
    widest = max(p.shape[1] for p in panels)
    panels = [np.pad(p, ((0, 8), (0, widest - p.shape[1]), (0, 0))) for p in panels]
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.vstack(panels), cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover
        raise InvalidInput(f"could not encode the montage as PNG for {out}")
    return atomic_write_bytes(target, buf.tobytes())
