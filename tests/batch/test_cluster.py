"""A batch on a two-node cluster (``ray.cluster_utils.Cluster``, one CPU each): the stages of two
captures run on both nodes."""

from __future__ import annotations

import shutil

from dbb_capture.batch.run import run_batch

from .tiny import need_ray, tiny_config


def test_stages_run_on_both_nodes(first_batch, batch_captures, tmp_path):
    ray = need_ray()
    from ray.cluster_utils import Cluster

    out, _ = first_batch
    new, caps = tmp_path / "out", tmp_path / "captures"
    for name in ("static", "dynamic"):       # datasets and runs as made: bundle and verify run
        shutil.copytree(out / name / "dataset", new / name / "dataset")
        shutil.copytree(out / name / "run", new / name / "run")
        shutil.copytree(batch_captures / name, caps / name)
    ray.shutdown()                           # the session's local Ray; the next test starts it again
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        ray.init(address=cluster.address, log_to_driver=False)
        summary = run_batch(caps, new, tiny_config(), live=False)
    finally:
        ray.shutdown()
        cluster.shutdown()
    assert summary.cluster.nodes == 2 and summary.cluster.cpus == 2
    assert [c.status for c in summary.captures] == ["ok", "ok"], [c.error for c in summary.captures]
    ran = [s for c in summary.captures for s in c.stages]
    assert [s.status for s in ran if s.stage in ("preprocess", "train")] == ["skipped"] * 4
    assert len({s.node_id for s in ran}) == 2, "every stage ran on one node"
