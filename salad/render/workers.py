"""Render workers: helper processes that draw part of a video's frames while this one draws the rest.

A frame from the software rasteriser is about half pyrender's Python and half rasterising, and one
process leaves the second core idle for much of it. A worker is another Python with its own GL
context: while this process draws a video's first frames and feeds the encoder, each idle worker
draws a later share and sends it back over a socket (a JSON header, then raw array bytes; nothing
is pickled). A worker still starting, busy with an abandoned render, or dead is not used, and a
share whose worker fails is drawn here: a render never depends on a worker.

    start(1)    # once, e.g. by a server at start-up (a worker takes ~2-3 s to get ready)
    ...         # every render of this process may use it
    stop()

The worker's own side is salad.render.worker_main.
"""
from __future__ import annotations

import atexit
import json
import logging
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import fields

import numpy as np

log = logging.getLogger("salad.render")
_HEADER = struct.Struct(">I")
_ARRAY_FIELDS = ("tint", "targets", "target_mask", "trajectory")     # video.Scene's optional arrays
# A worker's share is only worth its messages for renders of this many frames or more.
MIN_SHARED_FRAMES = 16
# This process's share of a render's frames with one worker (with k workers 2 * OWN_SHARE / (k + 1)): it
# also composes every frame and feeds the encoder. A 98-frame preview at 320 px on 2 cores took 0.36-0.39 s
# at 0.25-0.35, 0.44-0.45 at 0.45-0.55, 0.48 at 0.15, and 0.49-0.53 s without a worker.
OWN_SHARE = 0.3
# A worker that sends nothing for this long is taken for hung: it is stopped and its share drawn here.
FRAME_TIMEOUT_S = 30.0
MAX_WORKERS = 7

_workers: list[Worker] = []
_lock = threading.Lock()


# ------------------------------------------------------------------ messages

def send_message(sock: socket.socket, header: dict, arrays: list[np.ndarray] = ()) -> None:
    """A 4-byte length, the JSON header (with each array's dtype and shape), then the arrays' bytes."""
    arrays = [np.ascontiguousarray(a) for a in arrays]
    header = dict(header, arrays=[[a.dtype.str, list(a.shape)] for a in arrays])
    data = json.dumps(header).encode()
    sock.sendall(_HEADER.pack(len(data)) + data)
    for a in arrays:
        sock.sendall(memoryview(a).cast("B"))


def _recv_exact(sock: socket.socket, buf: memoryview) -> None:
    while len(buf):
        n = sock.recv_into(buf)
        if n == 0:
            raise EOFError("the other end closed the render socket")
        buf = buf[n:]


def recv_message(sock: socket.socket) -> tuple[dict, list[np.ndarray]]:
    size = bytearray(_HEADER.size)
    _recv_exact(sock, memoryview(size))
    data = bytearray(_HEADER.unpack(size)[0])
    _recv_exact(sock, memoryview(data))
    header = json.loads(data)
    arrays = []
    for dtype, shape in header.pop("arrays"):
        dt = np.dtype(dtype)
        if dt.hasobject:        # raw bytes never make Python objects
            raise ValueError(f"refusing an array of dtype {dt} in a render message")
        a = np.empty(shape, dt)
        if a.nbytes:
            _recv_exact(sock, memoryview(a).cast("B"))
        arrays.append(a)
    return header, arrays


def scene_message(scene) -> tuple[dict, list[np.ndarray]]:
    """A video.Scene -> (JSON-able header, arrays) for send_message (worker_main.scene_from_message reads it)."""
    header, arrays, names = {}, [], []
    for f in fields(scene):
        value = getattr(scene, f.name)
        if f.name == "motions":
            arrays += [np.asarray(m, np.float64) for m in value]
            names += ["motions"] * len(value)
        elif f.name in _ARRAY_FIELDS:
            if value is not None:
                arrays.append(np.asarray(value))
                names.append(f.name)
        else:
            header[f.name] = list(value) if isinstance(value, tuple) else value
    header["array_names"] = names
    return header, arrays


# ------------------------------------------------------------------ this process's side

class Job:
    """Frames of one share, as the worker sends them: frame(t) waits for frame t."""

    def __init__(self, worker: Worker, number: int):
        self.worker, self.number = worker, number
        self._frames: dict[int, dict[int, np.ndarray]] = {}
        self._cond = threading.Condition()
        self.done = False
        self.failed = False

    def put(self, t: int, images: dict[int, np.ndarray]) -> None:
        with self._cond:
            self._frames[t] = images
            self._cond.notify_all()

    def end(self, failed: bool) -> None:
        with self._cond:
            self.done, self.failed = True, self.failed or failed
            self._cond.notify_all()

    def frame(self, t: int) -> dict[int, np.ndarray] | None:
        """Frame t's panel images, or None once the worker has failed (this process then draws)."""
        with self._cond:
            while t not in self._frames and not self.done:
                if not self._cond.wait(FRAME_TIMEOUT_S) and t not in self._frames and not self.done:
                    log.warning("render worker %s sent nothing for %.0f s: stopping it", self.worker.pid,
                                FRAME_TIMEOUT_S)
                    self.failed = self.done = True
                    self.worker.close()
            return None if self.failed else self._frames.pop(t, None)


class Worker:
    """One render worker process and the thread that reads what it sends."""

    def __init__(self):
        from .backend import gl_backend

        gl_backend()      # the worker inherits this process's choice of GL platform (PYOPENGL_PLATFORM)
        ours, theirs = socket.socketpair()
        self._sock = ours
        self.process = subprocess.Popen(
            [sys.executable, "-m", "salad.render.worker_main", str(theirs.fileno())], pass_fds=(theirs.fileno(),),
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=_worker_env())
        theirs.close()
        self.pid = self.process.pid
        self.ready = threading.Event()
        self._job: Job | None = None
        self.jobs = 0       # shares it has been given
        self._state = threading.Lock()
        self._alive = True
        threading.Thread(target=self._read, name=f"render-worker-{self.pid}", daemon=True).start()

    @property
    def idle(self) -> bool:
        with self._state:
            return self._free()

    def _free(self) -> bool:
        """Alive, ready and without a share still drawing (call with _state held)."""
        return self._alive and self.ready.is_set() and (self._job is None or self._job.done)

    def draw(self, scene, panels: list[int], lo: int, hi: int, samples: int) -> Job | None:
        """Start drawing frames lo..hi-1 of `scene`'s `panels`; None if the worker cannot take it."""
        with self._state:
            if not self._free():
                return None
            self.jobs += 1
            job = self._job = Job(self, self.jobs)
        header, arrays = scene_message(scene)
        try:
            send_message(self._sock, {"op": "draw", "job": job.number, "scene": header, "panels": panels,
                                      "lo": lo, "hi": hi, "samples": samples}, arrays)
        except OSError:
            self.close()
            return None
        return job

    def _read(self) -> None:
        try:
            while True:
                header, arrays = recv_message(self._sock)
                if header.get("ready"):
                    self.ready.set()
                    continue
                job = self._job
                if job is None or header.get("job") != job.number:
                    continue
                if "t" in header:
                    job.put(header["t"], dict(zip(header["panels"], arrays)))
                else:
                    if header.get("error"):
                        log.warning("render worker %s: %s", self.pid, header["error"])
                    job.end(failed=bool(header.get("error")))
        except Exception as exc:     # EOF, a closed socket, a garbled message: the worker is of no more use
            if self._alive:
                log.warning("render worker %s stopped: %s: %s", self.pid, type(exc).__name__, exc)
        finally:
            self.close()

    def close(self) -> None:
        with self._state:
            self._alive = False
            job = self._job
        if job is not None:
            job.end(failed=True)
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()


def _worker_env() -> dict[str, str]:
    env = dict(os.environ)
    # Mesa's llvmpipe rasterises on LP_NUM_THREADS threads (one per core by default); a worker rasterising
    # on its own thread leaves the cores to this process and the encoder (the 98-frame preview: 0.40 s
    # against 0.45 with the default; no gain with this process on one thread too).
    env.setdefault("LP_NUM_THREADS", "0")
    return env


def start(n: int = 1) -> int:
    """Keep `n` render workers running (starting those missing, in the background); returns n."""
    if not 0 <= int(n) <= MAX_WORKERS:
        raise ValueError(f"render workers must be 0..{MAX_WORKERS}, got {n}")
    with _lock:
        _workers[:] = [w for w in _workers if w.process.poll() is None]
        while len(_workers) > n:
            _workers.pop().close()
        while len(_workers) < n:
            _workers.append(Worker())
    return n


def stop() -> None:
    """Stop every render worker."""
    with _lock:
        while _workers:
            _workers.pop().close()


def running() -> list[Worker]:
    with _lock:
        return list(_workers)


def wait_ready(count: int = 0, timeout_s: float = 60.0) -> None:
    """Return once at least `count` workers run and every one is ready for a render (TimeoutError after
    timeout_s, RuntimeError if one has exited): `count` for workers that another thread is still to start."""
    deadline = time.monotonic() + timeout_s
    while len(running()) < count or not all(w.idle for w in running()):
        exited = [w for w in running() if w.process.poll() is not None]
        if exited:
            raise RuntimeError(f"render worker {exited[0].pid} exited with status {exited[0].process.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"render workers not ready after {timeout_s:.0f} s")
        time.sleep(0.05)


atexit.register(stop)


def shares(scene, panels: list[int], total: int, samples: int) -> list[tuple[int, int, Job | None]]:
    """Split frames 0..total-1 of `scene` into contiguous shares: [(lo, hi, job)], this process's own
    first (job None), then one per idle worker, which starts drawing its `panels` at once."""
    idle = [w for w in running() if w.idle] if panels and total >= MIN_SHARED_FRAMES else []
    if not idle:
        return [(0, total, None)]
    own = int(round(total * 2 * OWN_SHARE / (len(idle) + 1)))
    bounds = np.linspace(own, total, len(idle) + 1).round().astype(int)
    plan = [(0, own, None)]
    for w, lo, hi in zip(idle, bounds[:-1], bounds[1:]):
        job = w.draw(scene, panels, int(lo), int(hi), samples) if hi > lo else None
        plan.append((int(lo), int(hi), job))
    return plan
