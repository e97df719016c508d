"""The loader: decode a keyframe's camera images and inject the cell's corruption, on demand.

A `CellSample` is the suite's own record of one frame in one cell (frame, family, severity, seed, what was
decoded); the planner never sees it. It receives `CellSample.view`, a read-only mapping camera -> image and
nothing else (SPEC section 11): no attribute, ``__dict__`` or view object leads back to the frame, its ground
truth, the family or the severity. Each camera is decoded and corrupted only when the planner reads it, so a
planner that reads three cameras costs three decodes; every delivered array is read-only. What a cell delivers
depends only on (seed, frame, camera, family, severity), and for frame_dropout on the frames before it in the same
cell, never on the worker layout.

`equals_clean` says, from the cell alone (family, severity, the planner's declared cameras, frame_dropout's
source frames) and without decoding or comparing a pixel, when a sample delivers exactly the clean images on
every camera a planner reads: the run then reuses the clean plan of a deterministic planner instead of asking it
again.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, ItemsView, Iterator, KeysView, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from types import MappingProxyType
from typing import TypeVar

import numpy as np

from .cells import DIAGNOSTIC, cell_id, is_input
from .constants import CAMERAS
from .corruptions.api import corrupt
from .corruptions.ladder import FAMILIES
from .corruptions.seeding import rng_for
from .corruptions.temporal import frame_lost
from .data.frame import Frame
from .errors import DataError

Decode = Callable[[Frame, str], np.ndarray]
T = TypeVar("T")


class DropoutState:
    """frame_dropout's hold-last-frame: for each camera, the frame whose image it last delivered.

    The state is the *source* frame, not pixels, so nothing is decoded for a camera the planner never reads.
    It resets at each new scene: a camera stream does not carry over between logs.
    """

    def __init__(self) -> None:
        self.scene: str | None = None
        self.source: dict[str, Frame | None] = {}

    def advance(self, frame: Frame, probability: float, seed: int, severity: int) -> dict[str, Frame | None]:
        if frame.scene_token != self.scene:
            self.scene, self.source = frame.scene_token, {}
        for cam in CAMERAS:
            lost = frame_lost(rng_for(seed, frame.token, cam, "frame_dropout", severity), probability)
            self.source[cam] = self.source.get(cam) if lost else frame
        return dict(self.source)


def _libc_memcmp() -> Callable[[int, int, int], int] | None:
    """The C library's memcmp (half the time of numpy's element-wise compare), or None where it is not found."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        memcmp = libc.memcmp
        memcmp.restype, memcmp.argtypes = ctypes.c_int, (ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
    except (OSError, AttributeError):  # pragma: no cover - a platform without a loadable C library
        return None
    return memcmp


_MEMCMP = _libc_memcmp()


def _same_bytes(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two C-contiguous arrays of one shape and dtype hold the same bytes (memcmp: about 0.1 ms for an
    800 x 450 image)."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if _MEMCMP is not None:
        return _MEMCMP(a.ctypes.data, b.ctypes.data, a.nbytes) == 0
    return bool(np.array_equal(a.reshape(-1).view(np.uint8), b.reshape(-1).view(np.uint8)))


class _Cameras(Mapping[str, np.ndarray]):
    """The planner's side of a sample: camera -> image through a closure, and nothing else.

    It is only ever handed out wrapped in a ``MappingProxyType`` (which exposes no route to it), and its views
    are built over plain data: the ``KeysView`` / ``ValuesView`` / ``ItemsView`` that ``Mapping`` would return
    keep a ``_mapping`` reference, which would lead back here and, through the closure, to the sample.
    """

    __slots__ = ("_read",)

    def __init__(self, read: Callable[[str], np.ndarray]) -> None:
        self._read = read

    def __getitem__(self, camera: str) -> np.ndarray:
        return self._read(camera)

    def __iter__(self) -> Iterator[str]:
        return iter(CAMERAS)

    def __len__(self) -> int:
        return len(CAMERAS)

    def __contains__(self, camera: object) -> bool:
        return camera in CAMERAS

    def keys(self) -> KeysView[str]:
        return dict.fromkeys(CAMERAS).keys()

    def values(self) -> tuple[np.ndarray, ...]:  # type: ignore[override] # reads every camera, like dict's would
        return tuple(self._read(cam) for cam in CAMERAS)

    def items(self) -> ItemsView[str, np.ndarray]:
        return {cam: self._read(cam) for cam in CAMERAS}.items()

    def __repr__(self) -> str:
        return f"<camera images: {', '.join(CAMERAS)}>"


def planner_view(read: Callable[[str], np.ndarray]) -> Mapping[str, np.ndarray]:
    """The read-only mapping camera -> image a planner receives, reading each camera through `read` on demand
    (the proxy exposes no route to the mapping behind it, hence none to `read` or its sample)."""
    return MappingProxyType(_Cameras(read))


def may_equal_clean(family: str, severity: int, cameras: tuple[str, ...]) -> bool:
    """Whether some frame of the cell may deliver the clean images on every camera of `cameras` (the planner's
    declared ones), decided from the cell alone; `CellSample.equals_clean` decides it per frame.

    blackout: when none of its cameras is read (S1-S3 for a front-only planner); frame_dropout: a frame where
    no read camera was dropped; any other ladder family changes every camera it touches, so only a planner that
    reads no camera. Never the diagnostic cells (clean itself; null and blind are the controls) nor the ego
    cells (the images are clean there, but the ego status the planner gets is not).
    """
    if family in DIAGNOSTIC or is_input(family) or family not in FAMILIES:
        return False
    if family == "blackout":
        return not set(cameras) & set(FAMILIES[family].value(severity))
    return family == "frame_dropout" or not cameras


class CellSample(Mapping[str, np.ndarray]):
    """The six degraded camera images of one frame for one cell, produced lazily and read-only.

    The planner gets a private copy of each image it reads; the image as produced is kept beside it, so that
    `written` can tell, after the call, whether the planner wrote into its input by any route (``setflags`` then
    a write, an in-place op on a ``torch.from_numpy`` view, a raw memory write). A write changes only that copy:
    it never reaches the decode cache or another cell. The planner gets `view`, never the sample itself.
    """

    def __init__(self, frame: Frame, family: str, severity: int, *, seed: int, decode: Decode,
                 unread: tuple[str, ...] = (), dropout: dict[str, Frame | None] | None = None) -> None:
        self.frame, self.family, self.severity, self.seed = frame, family, severity, seed
        self._decode, self._unread, self._dropout = decode, unread, dropout
        self._made: dict[str, np.ndarray] = {}  # camera -> the image as produced (never handed out)
        # camera -> (image as produced, the planner's copy), or what producing it raised: made ahead of the read
        # by `produce` (a prefetch thread), taken over by the first read; a camera never read is never delivered
        self._ready: dict[str, tuple[np.ndarray, np.ndarray] | Exception] = {}
        self._cache: dict[str, np.ndarray] = {}  # camera -> the planner's private copy
        self.seconds = {"decode": 0.0, "inject": 0.0, "check": 0.0}
        #: Data faults met while producing an image (missing, empty, truncated, wrong-size file): the frame is a
        #: data error whatever the planner then did (it may have caught the exception and planned without it).
        self.data_errors: list[str] = []
        #: Set by the run when the clean cell's plan was reused for this frame (nothing was read or predicted):
        #: the frame's index in the clean record, whose row of figures the frame then takes.
        self.reused_from: int | None = None
        #: Seconds the planner computed on this frame (its call, net of the images made lazily inside it; a
        #: batch's call shared evenly), set by the stream.
        self.called = 0.0

    def equals_clean(self, cameras: tuple[str, ...]) -> bool:
        """Whether this frame delivers the clean image on every camera of `cameras` (the planner's declared
        ones), from the cell's definition alone: no image is decoded or compared (see `may_equal_clean`). For
        frame_dropout, a read camera equals clean when its source is this very frame (not dropped, not held)."""
        if not may_equal_clean(self.family, self.severity, cameras):
            return False
        if self.family != "frame_dropout":
            return True
        source = self._dropout or {}
        return all((held := source.get(cam)) is not None and held.token == self.frame.token for cam in cameras)

    def __getitem__(self, camera: str) -> np.ndarray:
        if camera not in self._cache:
            if camera not in CAMERAS:
                raise KeyError(camera)
            try:
                ready = self._ready.pop(camera, None)
                if isinstance(ready, Exception):
                    raise ready
                self._made[camera], self._cache[camera] = ready or self._produced(camera)
            except DataError as exc:
                self.data_errors.append(str(exc))
                raise
        return self._cache[camera]

    def produce(self, cameras: tuple[str, ...]) -> None:
        """Make the images of `cameras` ahead of the planner's read (on a prefetch thread, before the sample is
        handed over): each is delivered, or what making it raised is raised, only when the planner reads it, so
        the frame's images, data faults and energy are what the serial path's lazy reads give."""
        for camera in cameras:
            if camera in self._cache or camera in self._ready:
                continue
            try:
                self._ready[camera] = self._produced(camera)
            except Exception as exc:  # noqa: BLE001 - raised again at the planner's read, as the lazy path would
                self._ready[camera] = exc

    @property
    def ahead(self) -> int:
        """The images made ahead and not yet read (`produce`)."""
        return sum(not isinstance(v, Exception) for v in self._ready.values())

    def _produced(self, camera: str) -> tuple[np.ndarray, np.ndarray]:
        """The camera's image as produced and the planner's private copy of it, both read-only."""
        image = np.ascontiguousarray(self._make(camera))
        image.setflags(write=False)
        start = time.perf_counter()
        copy = image.copy()
        copy.setflags(write=False)
        self.seconds["check"] += time.perf_counter() - start
        return image, copy

    @property
    def view(self) -> Mapping[str, np.ndarray]:
        """What the planner receives as `images`: a new read-only mapping over this sample's cameras (made per
        call and never stored here, so no reference cycle keeps a frame's images alive after the call)."""
        return planner_view(self.__getitem__)

    def written(self) -> list[str]:
        """The cameras whose delivered image no longer equals what was produced (the planner wrote into it)."""
        start = time.perf_counter()
        try:
            return [cam for cam, copy in self._cache.items() if not _same_bytes(copy, self._made[cam])]
        finally:
            self.seconds["check"] += time.perf_counter() - start

    def __iter__(self) -> Iterator[str]:
        return iter(CAMERAS)

    def __len__(self) -> int:
        return len(CAMERAS)

    def __repr__(self) -> str:
        return f"<CellSample {cell_id(self.family, self.severity)} frame {self.frame.token}>"

    @property
    def delivered(self) -> dict[str, np.ndarray]:
        """The images the planner actually read, as delivered (for the energy proxy)."""
        return dict(self._made)

    def _black(self, camera: str) -> np.ndarray:
        info = self.frame.cameras[camera]
        return np.zeros((info.height, info.width, 3), np.uint8)

    def _load(self, frame: Frame, camera: str) -> np.ndarray:
        start = time.perf_counter()
        try:
            return self._decode(frame, camera)
        finally:
            self.seconds["decode"] += time.perf_counter() - start

    def _make(self, camera: str) -> np.ndarray:
        family = self.family
        if family == "blind" or (family == "null" and camera in self._unread):
            return self._black(camera)
        if family in ("clean", "null") or is_input(family):  # the ego and command cells leave the images clean
            return self._load(self.frame, camera)
        if family == "blackout":
            return self._black(camera) if camera in FAMILIES[family].value(self.severity) \
                else self._load(self.frame, camera)
        if family == "frame_dropout":
            source = (self._dropout or {}).get(camera)
            return self._black(camera) if source is None else self._load(source, camera)
        clean = self._load(self.frame, camera)
        start = time.perf_counter()
        out = corrupt(clean, family, self.severity, seed=self.seed, frame=self.frame.token, camera=camera)
        self.seconds["inject"] += time.perf_counter() - start
        return out


def samples(frames: list[Frame], family: str, severity: int, *, seed: int, decode: Decode,
            unread: tuple[str, ...] = (), history: Sequence[Frame] = ()) -> Iterator[CellSample]:
    """The cell's samples in frame order (frame_dropout's state runs along them). `history`: the run's frames of
    the first frame's scene before it (a span that starts mid-scene); frame_dropout's state is advanced over them
    (loss draws only, nothing decoded), so every frame delivers the images a run from the scene's start gives."""
    state = DropoutState() if family == "frame_dropout" else None
    probability = FAMILIES[family].value(severity) if state else 0.0
    if state is not None:
        for frame in history:
            state.advance(frame, probability, seed, severity)
    for frame in frames:
        dropout = state.advance(frame, probability, seed, severity) if state else None
        yield CellSample(frame, family, severity, seed=seed, decode=decode, unread=unread, dropout=dropout)


def ahead(items: Iterator[tuple[CellSample, T]], cameras: tuple[str, ...], depth: int,
          wanted: Callable[[T], bool]) -> Iterator[tuple[CellSample, T]]:
    """`items` in their order, each sample's `cameras` made (`CellSample.produce`) on one thread beside the
    caller, up to `depth` frames ahead of the one handed out, where `wanted` says the sample will be read.

    Memory: at most `depth` frames' images made ahead of the caller's (up to six images and their copies each);
    `depth` 0 is the serial path, every image made lazily when read. `items` itself is drawn in order on the
    caller's thread (frame_dropout's state, the reuse decision), so nothing but when an image is made changes.
    """
    if depth <= 0:
        yield from items
        return
    pool = ThreadPoolExecutor(1, thread_name_prefix="drivedegrade-prefetch")
    queue: deque[tuple[CellSample, T, Future[None] | None]] = deque()
    try:
        for sample, extra in items:
            queue.append((sample, extra, pool.submit(sample.produce, cameras) if wanted(extra) else None))
            if len(queue) > depth:
                yield _ready(queue.popleft())
        while queue:
            yield _ready(queue.popleft())
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _ready(entry: tuple[CellSample, T, Future[None] | None]) -> tuple[CellSample, T]:
    """A queued sample once its images are made (the caller waits here, outside the planner's call)."""
    sample, extra, made = entry
    if made is not None:
        made.result()
    return sample, extra
