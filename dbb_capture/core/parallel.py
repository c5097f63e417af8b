"""Map per-frame work over spawned worker processes, with progress ticks back to the parent.

Frames are independent (pure functions over arrays), so a long clip is split into contiguous
segments, each decoded and processed in its own process (one thread each: one process per
core already). ``spawn``, not ``fork``: torch, PyAV and LibRaw threads do not survive a fork.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import threading
from concurrent.futures import ProcessPoolExecutor
from typing import Callable, Iterator, Sequence, TypeVar

import numpy as np

T = TypeVar("T")
R = TypeVar("R")

_queue = None  # set in each worker process by _init


def die_with_parent(parent: int | None = None) -> None:
    """Have the kernel kill this process when its parent (pid ``parent``, default the current
    one) dies, however it dies (Linux's parent-death signal; elsewhere a watchdog thread that
    polls the parent's pid)."""
    import signal
    import sys
    import threading
    import time

    parent = os.getppid() if parent is None else parent
    if os.getppid() != parent:                  # it died while this process started
        os._exit(1)
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1
        if ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL) == 0:
            if os.getppid() != parent:          # the parent died before the call
                os._exit(1)
            return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _init(queue, parent: int) -> None:
    import sys

    import cv2

    global _queue
    die_with_parent(parent)
    _queue = queue
    cv2.setNumThreads(1)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def report(n: int = 1) -> None:
    """From a worker: ``n`` more items done (no-op in the parent process)."""
    if _queue is not None:
        _queue.put(n)


@contextlib.contextmanager
def signals_held(signums: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Hold ``signums`` while the block runs, then deliver any that came to the handlers in place
    before it (main thread only; elsewhere a no-op, as Python runs handlers there only).

    A stop that lands while a worker is being spawned would cut the pipe the parent writes its
    start-up data to: the half-started child prints a traceback after the parent's last line, and
    it is not yet among the pool's processes that the stop kills.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    before = {s: signal.signal(s, lambda signum, frame: came.append(signum)) for s in signums}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(came):
            signal.raise_signal(s)


def split(indices: Sequence[int], parts: int) -> list[tuple[int, ...]]:
    """``indices`` cut into ``parts`` contiguous, nearly equal segments."""
    return [tuple(c.tolist()) for c in np.array_split(np.asarray(list(indices)), parts) if len(c)]


def map_spawned(fn: Callable[[T], R], tasks: Sequence[T], workers: int,
                tick: Callable[[int], None] | None = None) -> list[R]:
    """``[fn(t) for t in tasks]`` in ``workers`` spawned processes (results in task order).

    ``fn`` must be importable (module level) and call :func:`report` as it goes; ``tick`` gets
    those counts in the parent.
    """
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(q, os.getpid()))
    try:
        with signals_held():        # the pool spawns its workers as the tasks are submitted
            futures = [pool.submit(fn, t) for t in tasks]
        while True:
            try:
                n = q.get(timeout=0.1)
            except queue_mod.Empty:
                if all(f.done() for f in futures):
                    break
                continue
            if tick:
                tick(n)
        results = [f.result() for f in futures]
    except BaseException:
        # A stop (Ctrl-C, SIGTERM) or a failed task: the pool's own shutdown would wait for every
        # worker to finish its whole segment first (seconds to minutes); nothing of theirs is wanted.
        procs = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            proc.kill()
        raise
    pool.shutdown()
    q.close()
    return results
