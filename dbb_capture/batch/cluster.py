"""Ray for a batch: start a local instance or join a cluster, check that every node sees the
output folder, and what each stage's task asks for. Ray is imported here only, so the rest of
the package (and ``dbb-batch --help``) works without it."""

from __future__ import annotations

import logging
import os
import secrets
from pathlib import Path

from ..core.errors import DbbError
from ..core.outputs import write_bytes_atomic
from .config import BatchConfig, Resources
from .probe import sees
from .records import ClusterInfo, StageRecord
from .stages import StageTask, run_stage

MARKER = ".dbb-batch"             # OUT/.dbb-batch: the current batch's token
CHECK_SECONDS = 120.0             # every node must answer the filesystem check within this
LOCAL_OBJECT_STORE_BYTES = 256 * 2**20
# Failures worth another attempt besides a lost worker or node (Ray retries those by itself):
# a network filesystem or a service that did not answer. A DbbError is bad input: never retried.
TRANSIENT_ERRORS = (ConnectionError, TimeoutError)


def import_ray():
    """The ``ray`` module, or one clear error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise DbbError("dbb-batch needs Ray: pip install 'dbb-capture[ray]' (scripts/setup.sh installs it)") from None
    return ray


def connect(address: str | None) -> ClusterInfo:
    """Join the cluster at ``address`` (``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``), or start a
    local Ray over this machine's CPUs; a Ray already initialised in this process (tests) is used
    as it is. Worker output goes to Ray's logs, not the terminal (docs/batch.md)."""
    ray = import_ray()
    here = not ray.is_initialized()
    if here:
        opts = {"log_to_driver": False, "logging_level": logging.WARNING}
        try:
            if address is None:
                # Ray runs workers at nice 15; here they do the user's main work, as the single
                # commands do at nice 0 (RAY_worker_niceness set by the user wins).
                os.environ.setdefault("RAY_worker_niceness", "0")
                # "local": a new instance even where `ray start` left one running. Tasks return
                # small records (the data moves through the shared folder): a small object store.
                ray.init(address="local", num_cpus=os.cpu_count() or 1, include_dashboard=False,
                         object_store_memory=LOCAL_OBJECT_STORE_BYTES, **opts)
            else:
                ray.init(address=address, **opts)
        except Exception as e:  # noqa: BLE001 - Ray raises ConnectionError, ValueError, RuntimeError ...
            where = f"the Ray cluster at {address}" if address else "a local Ray"
            raise DbbError(f"cannot start or join {where}: {' '.join(str(e).split())[:300]}") from None
    nodes = alive_nodes()
    total = ray.cluster_resources()
    return ClusterInfo(address or ("local" if here else "this process's Ray"), len(nodes),
                       float(total.get("CPU", 0)), float(total.get("GPU", 0)),
                       max((float(n["Resources"].get("CPU", 0)) for n in nodes), default=0.0), here)


def disconnect(info: ClusterInfo) -> None:
    """Leave Ray if this batch connected: a local Ray stops, a joined cluster stays up."""
    import ray

    if info.connected_here:
        ray.shutdown()


def alive_nodes() -> list[dict]:
    import ray

    return [n for n in ray.nodes() if n.get("Alive")]


def resources(cfg: BatchConfig, info: ClusterInfo) -> Resources:
    """Each stage's request on this cluster: preprocess at most the largest node's CPUs (else it
    could never be placed); a GPU per training where the cluster has GPUs (``gpus_per_train``)."""
    gpus = cfg.gpus_per_train if cfg.gpus_per_train is not None else (1.0 if info.gpus > 0 else 0.0)
    if gpus > 0 and info.gpus == 0:
        raise DbbError(f"{{=gpus_per_train}} {gpus:g}: the cluster has no GPU (give 0 to train on CPUs)")
    if gpus > info.gpus > 0 and gpus > 1:
        raise DbbError(f"{{=gpus_per_train}} {gpus:g}: more than the cluster's {info.gpus:g} GPUs")
    cpus = cfg.preprocess_cpus if info.max_node_cpus <= 0 else min(cfg.preprocess_cpus, info.max_node_cpus)
    return Resources(preprocess_cpus=cpus, train_gpus=gpus)


def claim_output(out: Path, captures: Path) -> tuple[Path, str]:
    """Write ``OUT/.dbb-batch`` with a new token and check from a task on every node that it
    reads the same file and sees the captures: both must be on a filesystem every node mounts
    at the same path. Returns the marker and its token."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    out = Path(out).resolve()
    try:
        out.mkdir(parents=True, exist_ok=True)
        token = secrets.token_hex(8)
        write_bytes_atomic(out / MARKER, (token + "\n").encode())
    except OSError as e:
        raise DbbError(f"cannot write the output folder {out}: {e.strerror}") from None
    probe = ray.remote(sees)
    refs = {probe.options(num_cpus=0, max_retries=1, scheduling_strategy=NodeAffinitySchedulingStrategy(
        n["NodeID"], soft=False)).remote(str(out / MARKER), token, str(Path(captures).resolve())): n
        for n in alive_nodes()}
    ready, late = ray.wait(list(refs), num_returns=len(refs), timeout=CHECK_SECONDS)
    if late:
        raise DbbError(f"node {refs[late[0]]['NodeManagerAddress']} did not answer the output-folder check "
                       f"in {CHECK_SECONDS:.0f} s")
    for ref in ready:
        try:
            host, problem = ray.get(ref)
        except Exception as e:  # noqa: BLE001 - e.g. the node cannot import the toolkit
            ip = refs[ref]["NodeManagerAddress"]
            raise DbbError(f"node {ip} cannot run the toolkit ({type(e).__name__}): install dbb-capture[ray] "
                           f"on every node (docs/batch.md)") from None
        if problem:
            raise DbbError(f"node {host} ({refs[ref]['NodeManagerAddress']}): {problem}: OUT and CAPTURES_DIR "
                           f"must be on a filesystem every node mounts at the same path (docs/batch.md)")
    return out / MARKER, token


def _stage_task(task: StageTask) -> StageRecord:
    """The Ray task of one stage: :func:`run_stage` with the node it ran on."""
    import ray

    ctx = ray.get_runtime_context()
    return run_stage(task, ctx.get_node_id(), ray.util.get_node_ip_address())


class StageLauncher:
    """Submits stage tasks with each stage's resources and the batch's retries."""

    def __init__(self, retries: int):
        import ray

        self._remote = ray.remote(_stage_task)
        self.retries = retries

    def submit(self, task: StageTask):
        """Start ``task`` on the cluster; returns its ObjectRef."""
        r = task.resources
        return self._remote.options(
            name=f"{task.stage} {task.job.name}", num_cpus=r.cpus(task.stage), num_gpus=r.gpus(task.stage),
            max_retries=self.retries, retry_exceptions=list(TRANSIENT_ERRORS)).remote(task)
