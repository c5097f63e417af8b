"""Map per-frame work over spawned worker processes, with progress ticks back to the parent.

Frames are independent (pure functions over arrays), so a long clip is split into contiguous
segments, each decoded and processed in its own process (one thread each: one process per
core already). ``spawn``, not ``fork``: torch, PyAV and LibRaw threads do not survive a fork.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queue_mod
from concurrent.futures import ProcessPoolExecutor
from typing import Callable, Sequence, TypeVar

import numpy as np

T = TypeVar("T")
R = TypeVar("R")

_queue = None  # set in each worker process by _init


def _init(queue) -> None:
    import sys

    import cv2

    global _queue
    _queue = queue
    cv2.setNumThreads(1)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def report(n: int = 1) -> None:
    """From a worker: ``n`` more items done (no-op in the parent process)."""
    if _queue is not None:
        _queue.put(n)


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
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(q,)) as pool:
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
    q.close()
    return results
