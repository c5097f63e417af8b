"""Spawned workers: a stop in the parent ends them at once, not after their whole segment."""

from __future__ import annotations

import os
import signal
import time

import pytest

from dbb_capture.core.parallel import map_spawned, report, signals_held


def _slow(seconds: float) -> float:
    report(1)
    time.sleep(seconds)
    return seconds


def test_a_stop_in_the_parent_ends_the_workers_at_once():
    def stop(_n: int) -> None:          # Ctrl-C or SIGTERM (cli.common) arrive as KeyboardInterrupt
        raise KeyboardInterrupt

    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        map_spawned(_slow, [60.0, 60.0], 2, stop)
    assert time.monotonic() - t0 < 30      # the pool's own shutdown would wait the workers' 60 s
    assert map_spawned(_slow, [0.0, 0.0], 2) == [0.0, 0.0]


def test_a_stop_while_held_arrives_once_the_block_ends():
    def stop(signum, frame):
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGTERM, stop)
    got = []
    try:
        with pytest.raises(KeyboardInterrupt):
            with signals_held():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)            # the handler would have run by now
                got.append("block finished")
        assert got == ["block finished"]
        assert signal.getsignal(signal.SIGTERM) is stop
    finally:
        signal.signal(signal.SIGTERM, before)
