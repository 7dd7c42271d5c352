"""The one thread the studio runs its model on.

torch's CPU intra-op pool is an OpenMP team per calling thread, and once a second thread had run
a parallel torch op, every team slowed down (OpenMP stops spinning between a team's barriers
when it manages more threads than there are cores). Gradio runs each event on a worker thread of
its own, so the studio sampled at half speed or worse: the 50-step teacher took 2.9-3.2 s per
motion on a worker thread against 1.4-1.5 s on the thread that had loaded it, the student
0.27-0.48 s against 0.10-0.23 (2 cores; assets/RESULTS.md, *Limitations, in detail*, studio latency). So the studio
loads the pipeline on this thread, runs every model call here, one at a time, and leaves every
other thread one core's worth of torch (`own_torch`).
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

import torch

T = TypeVar("T")
# own_torch's change is process-wide: the count before the first owner, and how many own it now
_owners_lock = threading.Lock()
_owners = 0
_count_before = 0


class ModelThread:
    def __init__(self):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="salad-model")
        self._thread: threading.Thread = self._pool.submit(threading.current_thread).result()
        # torch gives a thread its count from the process-wide one at its first use: fix it now,
        # before own_torch lowers that one (load_pipeline(threads=...) on this thread sets it again)
        self.run(torch.get_num_threads)
        self._owns = False

    def run(self, fn: Callable[..., T], *args, **kwargs) -> T:
        """fn(*args, **kwargs) on the model thread, waited for: its value, or its exception raised
        here. Called from the model thread itself, it runs fn directly (no deadlock)."""
        if threading.current_thread() is self._thread:
            return fn(*args, **kwargs)
        return self._pool.submit(fn, *args, **kwargs).result()

    def own_torch(self) -> None:
        """Keep torch's multi-core ops to the model thread: the calling thread, and every thread that
        runs its first torch op from now on, get one intra-op thread (torch keeps the count per
        thread once a thread has used it). When the last owner closes, the thread closing it gets
        the count from before back."""
        global _owners, _count_before
        if self._owns:
            return
        with _owners_lock:
            if _owners == 0:
                _count_before = torch.get_num_threads()
                torch.set_num_threads(1)
            _owners += 1
        self._owns = True

    def close(self) -> None:
        global _owners
        self._pool.shutdown(wait=False, cancel_futures=True)
        if not self._owns:
            return
        self._owns = False
        with _owners_lock:
            _owners -= 1
            if _owners == 0:
                torch.set_num_threads(_count_before)
