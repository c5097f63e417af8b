"""The render worker's dynamic canvas: one stepper, each client's rollout swapped in and out."""

from __future__ import annotations

import numpy as np

from dbb_capture.bundle.manifest import open_bundle
from dbb_capture.serve.worker import DynamicCanvas, Job


def test_each_client_keeps_its_own_steps_and_warm_up(dynamic_bundle):
    with open_bundle(dynamic_bundle) as b:
        canvas = DynamicCanvas(b, threads=1)
        assert "t" in canvas.state_keys                 # the warm-up's step count is per rollout
        fps = canvas.fps
        eye = np.asarray(b.manifest.center, float) + np.array([0.0, -0.6, 0.3])
        job = lambda client, at: Job(client, (client,), eye, 64, now=at / fps)     # ``at`` in frames
        assert canvas.render(job(1, 0.0))[2] == 0
        assert canvas.render(job(1, 5.5))[2] == 5
        assert canvas.render(job(2, 5.0))[2] == 0       # a new client starts at its own first frame
        assert canvas.render(job(2, 7.5))[2] == 2
        assert canvas.render(job(1, 6.5))[2] == 6
        assert canvas.rollouts[1].after["t"] == 6 and canvas.rollouts[2].after["t"] == 2
