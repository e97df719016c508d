"""`--drivedegrade-isolate`: the planner in a child process that receives only its inputs (issue 37).

In process, planner code can find which cell is running: the cell's family and severity are in the locals of
the frames that call ``predict`` (pytest's item, the stream's sample), in the objects the garbage collector
holds and in ``PYTEST_CURRENT_TEST``. Under this option the planner is built and called only in a child
process (`serve`), started with a clean environment (`isolated.clean_environment`: no ``PYTEST_*`` variable,
no signing key), whose stack holds this module's loop and nothing of the run. The stream, the corruption and
the scoring stay in the worker; `ChildPlanner` stands in for the planner there, and every call (``predict``,
``predict_batch``, ``reset``) sends the child the frame's inputs: the ego status, the command, the frame context
when ``predict`` takes one, and each camera image when the planner reads it (a round trip per camera, so the
images it reads, its data faults and its energy are the in-process run's). Images travel through a memfd both
processes map (`SharedImages`; ``benchmarks/isolation.py`` measures it against a pipe of raw buffers).

A child that ends (``os._exit``, a crash) or is stopped at the timeout fails the call it was in, naming its pid
and exit status; the next call starts a new one, up to `RESTARTS` times a cell, after which the cell's calls fail.
"""

from __future__ import annotations

import builtins
import mmap
import os
import pickle
import socket
import subprocess
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from ..data.context import FrameContext
from ..errors import DataError, DriveDegradeError
from ..loader import planner_view
from ..run import PlannerApart

#: The planner's optional attributes the stand-in mirrors, so the suite reads them as it reads the planner's.
MIRRORED = ("cameras", "name", "poses", "deterministic", "lidar")
#: Child processes a cell may start after one ended (a crash, os._exit, a timeout); `new_cell` counts anew.
RESTARTS = 3
START_SECONDS = 600.0  #: seconds the child may take to open the data and build the planner
#: Seconds past --drivedegrade-timeout the worker waits for a call's answer before it stops the child (the
#: timeout's own SIGALRM, in this process, normally ends the wait first).
GRACE_SECONDS = 5.0


#: Prefixes of the variables a planner's process never gets: pytest's and xdist's (``PYTEST_CURRENT_TEST`` names
#: the running cell), the signing key (refused anyway) and the device (the child sets it from the run's settings).
#: A user's own variables pass, ``DRIVEDEGRADE_``-named ones included: none of the suite's names the cell.
UNCLEAN_PREFIXES = ("PYTEST_", "DRIVEDEGRADE_SIGNING_KEY", "DRIVEDEGRADE_DEVICE")


def clean_environment() -> dict[str, str]:
    """The environment a process that runs planner code starts with (the pre-flight's, `childplanner`'s): this
    one's without `UNCLEAN_PREFIXES`. The kernel keeps it as the child's ``/proc/PID/environ``."""
    return {k: v for k, v in os.environ.items() if not k.upper().startswith(UNCLEAN_PREFIXES)}


Described = dict[str, Any]  #: what the child says of the planner it built
Message = tuple[Any, ...]  #: one message across the socket: a call, a read, an answer


class ChildEnded(DriveDegradeError):
    """The planner's process ended (or was stopped) during a call: the call fails, naming the process."""


class SharedImages:
    """A memfd mapped by both processes: the worker writes each image a call reads at the next free offset (the
    call's images stay there until it ends, so the child can tell a write into its copy), the child copies it
    out. It grows (ftruncate) when a call needs more; the child maps it again when an offset lies past its map."""

    def __init__(self, fd: int | None = None) -> None:
        self.fd = os.memfd_create("drivedegrade-images") if fd is None else fd
        self.map: mmap.mmap | None = None
        self.used = 0

    def _ensure(self, size: int, grow: bool) -> mmap.mmap:
        """The map, at least `size` bytes: grown by the worker (`grow`); mapped again by the child, whose old map
        stays alive while the call's images still view it."""
        if self.map is None or len(self.map) < size:
            if grow:
                os.ftruncate(self.fd, max(size, 2 * (len(self.map) if self.map else 0), 1 << 20))
                if self.map is not None:
                    self.map.close()
            self.map = mmap.mmap(self.fd, os.fstat(self.fd).st_size)
        return self.map

    def put(self, image: np.ndarray) -> tuple[int, tuple[int, ...], str]:
        data = np.ascontiguousarray(image)
        offset = self.used
        target = self._ensure(offset + data.nbytes, grow=True)
        target[offset:offset + data.nbytes] = data.reshape(-1).view(np.uint8).data
        self.used = offset + data.nbytes
        return offset, data.shape, data.dtype.str

    def get(self, offset: int, shape: tuple[int, ...], dtype: str) -> tuple[np.ndarray, np.ndarray]:
        """The image as sent (a view of the map, for the written check) and the planner's read-only copy."""
        kind = np.dtype(dtype)
        size = int(np.prod(shape)) * kind.itemsize
        sent = np.frombuffer(self._ensure(offset + size, grow=False), kind, int(np.prod(shape)), offset).reshape(shape)
        copy = sent.copy()
        copy.setflags(write=False)
        return sent, copy

    def close(self) -> None:
        if self.map is not None:
            self.map.close()
        os.close(self.fd)


# --- the wire: what crosses between the processes ----------------------------------------------------------------

def pack_context(context: FrameContext | None) -> FrameContext | None:
    """The context as pickle can carry it (its read-only mappings as dicts)."""
    if context is None:
        return None
    return replace(context, calibration=dict(context.calibration),
                   lidar2img=None if context.lidar2img is None else dict(context.lidar2img))


def unpack_context(context: FrameContext | None) -> FrameContext | None:
    """The context as the planner gets it in process: mappings read-only, every array read-only."""
    if context is None:
        return None
    for value in (context.ego2global, context.can_bus, context.lidar2ego,
                  *(context.lidar2img or {}).values(),
                  *(a for c in context.calibration.values() for a in (c.intrinsic, c.sensor2ego))):
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    return replace(context, calibration=MappingProxyType(dict(context.calibration)),
                   lidar2img=None if context.lidar2img is None else MappingProxyType(dict(context.lidar2img)))


def _exception(name: str, message: str, data: bool) -> Exception:
    """An exception that reads as the one the planner raised in the child (its class name and message; a
    subclass of the builtin of that name, or of DataError, so the stream tells them apart as in process)."""
    base = DataError if data else getattr(builtins, name, Exception)
    if not (isinstance(base, type) and issubclass(base, Exception)):
        base = Exception
    cls = type(name, (base,), {"__str__": lambda self: message, "__module__": "planner"})
    return cls(message)


def _portable(value: object) -> object:
    """A returned plan as pickle can carry it: a tensor as numpy (`planning.to_numpy`), anything pickle refuses
    as its type's name (the plan check then says it is not an array)."""
    from ..planning import to_numpy

    value = to_numpy(value)
    try:
        pickle.dumps(value)
    except Exception:  # noqa: BLE001 - any object may come back from predict
        return f"<unpicklable {type(value).__name__}>"
    return value


# --- the worker's side ---------------------------------------------------------------------------------------------

#: Starts a child over the images' memfd: its process, the connection to it and what it said of the planner.
Launch = Callable[[SharedImages], tuple["subprocess.Popen[bytes]", Connection, Described]]


class ChildPlanner(PlannerApart):
    """The worker's stand-in for a planner built in a child: its mirrored attributes, its fingerprint as the
    child computed it, and every call forwarded (`start_child_planner` makes the subclass that has exactly the
    planner's optional methods, so the suite calls it as it would call the planner)."""

    def __init__(self, launch: Launch, timeout: float, images: SharedImages,
                 started: tuple[subprocess.Popen[bytes], Connection], described: Described) -> None:
        self.launch, self.timeout, self.images = launch, timeout, images
        self.process: subprocess.Popen[bytes] | None = started[0]
        self.conn: Connection | None = started[1]
        self.described, self.restarts = described, 0
        self.apart_fingerprint = str(described.get("fingerprint", ""))

    def new_cell(self) -> None:  # `RESTARTS` counted anew
        self.restarts = 0

    @property
    def pid(self) -> int:  # the child's, now
        return int(self.described["pid"])

    def _predict(self, images: Mapping[str, np.ndarray], ego: object, cmd: object) -> object:
        return self._call(("predict", ego, cmd, None), [images])

    def _predict_context(self, images: Mapping[str, np.ndarray], ego: object, cmd: object,
                         context: FrameContext | None = None) -> object:
        return self._call(("predict", ego, cmd, pack_context(context)), [images])

    def _predict_batch(self, images: Sequence[Mapping[str, np.ndarray]], egos: Sequence[object],
                       cmds: Sequence[object], contexts: Sequence[FrameContext | None] | None = None) -> object:
        packed = None if contexts is None else [pack_context(c) for c in contexts]
        return self._call(("batch", list(egos), list(cmds), packed), list(images))

    def _reset(self, scene_token: str) -> None:
        self._call(("reset", scene_token), [])

    # --- the exchange ------------------------------------------------------------------------------------------

    def _call(self, message: tuple[object, ...], views: Sequence[Mapping[str, np.ndarray]]) -> object:
        """Send one call, serve the child's reads of `views` until it answers; the plan, or the planner's
        exception raised again here. Anything that interrupts the exchange (the timeout) stops the child."""
        conn = self._connection()
        self.images.used = 0
        try:
            conn.send(message)
            reply = self._receive(conn, str(message[0]))
            while reply[0] == "image":
                self._serve_image(conn, views, int(reply[1]), str(reply[2]))
                reply = self._receive(conn, str(message[0]))
        except BaseException:
            self._stop()
            raise
        _mark_written(views, reply[-1])
        if reply[0] == "raised":
            raise _exception(str(reply[1]), str(reply[2]), bool(reply[3]))
        return reply[1]

    def _serve_image(self, conn: Connection, views: Sequence[Mapping[str, np.ndarray]], index: int,
                     camera: str) -> None:
        try:
            image = views[index][camera]
        except Exception as exc:  # noqa: BLE001 - a data fault (or any read failure) is raised in the child
            conn.send(("error", type(exc).__name__, str(exc), isinstance(exc, DataError)))
            return
        conn.send(("image", *self.images.put(np.asarray(image))))

    def _receive(self, conn: Connection, what: str) -> Message:
        limit = self.timeout + GRACE_SECONDS if self.timeout > 0 else None
        if not conn.poll(limit):
            self._stop()
            raise ChildEnded(f"the planner's process (pid {self.pid}) did not answer {what}() within {limit:g} s; "
                             "it was stopped")
        try:
            return tuple(conn.recv())
        except (EOFError, OSError):
            status = self._stop()
            raise ChildEnded(f"the planner's process (pid {self.pid}) ended during {what}() (exit status {status}): "
                             "planner code that ends its process (os._exit, a crash) fails its call") from None

    def _connection(self) -> Connection:
        if self.conn is not None:
            return self.conn
        if self.restarts >= RESTARTS:
            raise ChildEnded(f"the planner's process ended {self.restarts + 1} times in this cell; no other is "
                             "started before the next cell")
        self.restarts += 1
        process, conn, described = self.launch(self.images)
        self.process, self.conn = process, conn
        if "error" in described or described.get("fingerprint") != self.apart_fingerprint:
            self._stop()
            raise ChildEnded(f"the planner's new process could not build the same planner: "
                             f"{described.get('error', 'its fingerprint differs')}")
        self.described = described
        return conn

    def _stop(self) -> int | None:  # end the child now (its call is lost); its exit status
        process, conn, self.process, self.conn = self.process, self.conn, None, None
        if conn is not None:
            conn.close()
        if process is None:
            return None
        if process.poll() is None:
            process.kill()
        return process.wait()

    def close(self) -> list[str]:
        """Tear the planner's fixtures down in the child and end it; a line per teardown problem."""
        conn = self.conn
        lines: list[str] = []
        if conn is not None:
            try:
                conn.send(("stop",))
                if conn.poll(START_SECONDS):
                    lines = list(conn.recv()[1])
            except (EOFError, OSError):
                lines = ["the planner's process ended before its fixtures' teardown"]
        if self.process is not None:
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                pass
        self._stop()
        self.images.close()
        return lines


def _mark_written(views: Sequence[Mapping[str, np.ndarray]], written: Sequence[tuple[int, str]]) -> None:
    """The child found that the planner wrote into its copy of these images: change this process's copy too,
    so the stream's check (`CellSample.written`) names the write as it would in process."""
    for index, camera in written:
        image = views[index][camera]
        try:
            image.setflags(write=True)
            image.reshape(-1).view(np.uint8)[:1] ^= 0xFF
            image.setflags(write=False)
        except (ValueError, AttributeError):  # an image this process cannot write (not the stream's copy)
            continue


def start_child_planner(launch: Launch, timeout: float) -> ChildPlanner:
    """Start the child and return the stand-in; DriveDegradeError saying why the planner cannot be built."""
    images = SharedImages()
    process, conn, described = launch(images)
    if "error" in described:
        for end in (conn.close, process.kill, process.wait, images.close):
            end()
        raise DriveDegradeError(str(described["error"]))
    body: Described = dict(described["attributes"])
    body["predict"] = ChildPlanner._predict_context if described["takes_context"] else ChildPlanner._predict
    if described["resets"]:
        body["reset"] = ChildPlanner._reset
    if described["batches"]:
        body["predict_batch"] = ChildPlanner._predict_batch
    cls = type("IsolatedPlanner", (ChildPlanner,), body)
    return cls(launch, timeout, images, (process, conn), described)


def spawn(request: Described, images: SharedImages) -> tuple[subprocess.Popen[bytes], Connection, Described]:
    """`Launch`: the child (``python -m`` this module) with a clean environment, given the socket and the
    memfd by descriptor and `request` (`ActorRun`'s fields, the planner file) as its first message."""
    mine, theirs = socket.socketpair()
    process = subprocess.Popen([sys.executable, "-m", __name__, str(theirs.fileno()), str(images.fd)],
                               env=clean_environment(), pass_fds=(theirs.fileno(), images.fd),
                               stdin=subprocess.DEVNULL)
    theirs.close()
    conn = Connection(mine.detach())
    conn.send(request)
    if not conn.poll(START_SECONDS):
        process.kill()
        return process, conn, {"error": f"the planner's process did not build the planner within {START_SECONDS:g} s"}
    try:
        return process, conn, dict(conn.recv())
    except (EOFError, OSError):
        status = process.wait()
        return process, conn, {"error": f"the planner's process ended (exit status {status}) while building the "
                                        "planner: planner code that ends its process fails the run"}


# --- the child's side ----------------------------------------------------------------------------------------------

class _Reads:
    """One call's images in the child: each asked of the worker when the planner first reads it, copied out of
    the memfd, kept beside what was sent (for `written`)."""

    def __init__(self, conn: Connection, shared: SharedImages, index: int) -> None:
        self.conn, self.shared, self.index = conn, shared, index
        self.sent: dict[str, np.ndarray] = {}
        self.copies: dict[str, np.ndarray] = {}

    def read(self, camera: str) -> np.ndarray:
        from ..constants import CAMERAS

        if camera not in self.copies:
            if camera not in CAMERAS:
                raise KeyError(camera)
            self.conn.send(("image", self.index, camera))
            reply = self.conn.recv()
            if reply[0] == "error":
                raise _exception(reply[1], reply[2], reply[3])
            self.sent[camera], self.copies[camera] = self.shared.get(reply[1], tuple(reply[2]), reply[3])
        return self.copies[camera]

    def written(self) -> list[tuple[int, str]]:
        return [(self.index, cam) for cam, copy in self.copies.items()
                if not np.array_equal(copy.reshape(-1).view(np.uint8), self.sent[cam].reshape(-1).view(np.uint8))]


def _ego(ego: object) -> object:  # read-only, as in process
    past = getattr(ego, "past_xy", None)
    if isinstance(past, np.ndarray):
        past.setflags(write=False)
    return ego


def _answer(planner: object, conn: Connection, shared: SharedImages, message: Message,
            takes_context: bool) -> Message:
    """One call of the planner on the inputs of `message`: ("done", plan, written) or ("raised", ...)."""
    reads: list[_Reads] = []
    try:
        if message[0] == "reset":
            getattr(planner, "reset")(message[1])  # noqa: B009 - optional: not in the Planner protocol
            return ("done", None, [])
        if message[0] == "predict":
            reads = [_Reads(conn, shared, 0)]
            args = (planner_view(reads[0].read), _ego(message[1]), message[2])
            predict = getattr(planner, "predict")  # noqa: B009 - the stand-in's own check found it
            raw = predict(*args, context=unpack_context(message[3])) if takes_context else predict(*args)
            return ("done", _portable(raw), reads[0].written())
        reads = [_Reads(conn, shared, i) for i in range(len(message[1]))]
        contexts = None if message[3] is None else [unpack_context(c) for c in message[3]]
        views = [planner_view(r.read) for r in reads]
        raw = getattr(planner, "predict_batch")(views, [_ego(e) for e in message[1]], message[2], contexts)  # noqa: B009
        plans = [_portable(p) for p in raw] if isinstance(raw, (list, tuple)) else _portable(raw)
        return ("done", plans, [w for r in reads for w in r.written()])
    except Exception as exc:  # noqa: BLE001 - the planner's failure, raised again in the worker
        return ("raised", type(exc).__name__, str(exc), isinstance(exc, DataError),
                [w for r in reads for w in r.written()])


def _attributes(planner: object) -> dict[str, object]:
    out = {}
    for name in MIRRORED:
        try:
            value = getattr(planner, name)
            pickle.dumps(value)
        except Exception:  # noqa: BLE001 - absent, or a property that raises, or not picklable: not mirrored
            continue
        out[name] = value
    return out


def serve(conn: Connection, shared: SharedImages) -> int:
    """The child: build the planner as a Ray actor does (`rayactor.PlannerActor`), say what it is, then answer
    calls until told to stop."""
    from ..rayactor import ActorRun, PlannerActor
    from .actors import PlannerFile

    request = conn.recv()
    build = PlannerFile(Path(request["collect_path"]), request["module"], option="--drivedegrade-isolate")
    actor = PlannerActor(ActorRun(**request["run"]), build, request["default_name"])
    described = actor.start()
    if "error" not in described:
        import cv2

        if request["opencv_threads"]:  # the worker's share (`pacing.opencv_share`), as in process
            cv2.setNumThreads(int(request["opencv_threads"]))
        described.update(attributes=_attributes(actor.planner),
                         batches=callable(getattr(actor.planner, "predict_batch", None)))
    conn.send(described)
    if "error" in described:
        return 0
    takes_context = bool(described["takes_context"])
    while True:
        try:
            message = conn.recv()
        except EOFError:
            return 0
        if message[0] == "stop":
            conn.send(("stopped", actor.stop()))
            return 0
        conn.send(_answer(actor.planner, conn, shared, message, takes_context))


if __name__ == "__main__":  # pragma: no cover - started by `spawn`
    raise SystemExit(serve(Connection(int(sys.argv[1])), SharedImages(int(sys.argv[2]))))
