"""``dbb-batch``: many captures through the whole pipeline on Ray (docs/batch.md)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from .common import DbbCommand


@click.command(cls=DbbCommand, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.argument("captures_dir", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Output folder: OUT/<capture>/{dataset,run,bundle} and OUT/summary.json; on a cluster, "
                   "a folder every node mounts at the same path.")
@click.option("--address", default=None, metavar="auto|HOST:PORT|ray://HOST:PORT",
              help="Join this Ray cluster (default: start a local Ray over this machine's CPUs).")
@click.option("--kind", "default_kind", type=click.Choice(["static", "dynamic"]), default="static",
              show_default=True, help="Kind of the captures whose object.json has no \"kind\".")
@click.option("--static-minutes", type=float, default=10.0, show_default=True, metavar="M",
              help="Training budget of each static capture (dbb-train plenoctree).")
@click.option("--dynamic-minutes", type=float, default=15.0, show_default=True, metavar="M",
              help="Training budget of each dynamic capture (dbb-train rssm).")
@click.option("--background-minutes", type=click.FloatRange(min=0.05), default=2.0, show_default=True, metavar="M",
              help="Training budget of each capture's room field (preprocess).")
@click.option("--gpus-per-train", type=click.FloatRange(min=0), default=None, metavar="G",
              help="GPUs each training asks for (fractions share one; default: 1 where the cluster has GPUs, "
                   "else 0).")
@click.option("--preprocess-cpus", type=click.IntRange(min=1), default=2, show_default=True, metavar="N",
              help="CPUs each preprocess asks for (and its decoding processes).")
@click.option("--retries", type=click.IntRange(min=0), default=2, show_default=True, metavar="N",
              help="Run a stage again up to N times when its worker or node is lost.")
@click.option("--force", is_flag=True, help="Redo every stage of every capture, even where outputs are complete.")
@click.option("--static-steps", type=click.IntRange(min=1), default=None, hidden=True,
              help="Training steps instead of minutes for static captures (reproducible runs, benchmarks).")
@click.option("--dynamic-steps", type=click.IntRange(min=1), default=None, hidden=True,
              help="Training steps instead of minutes for dynamic captures.")
@click.option("--background-steps", type=click.IntRange(min=1), default=None, hidden=True,
              help="Room-field steps instead of minutes.")
def main(captures_dir, out, address, default_kind, static_minutes, dynamic_minutes, background_minutes,
         gpus_per_train, preprocess_cpus, retries, force, static_steps, dynamic_steps, background_steps) -> int:
    """Run every capture folder inside CAPTURES_DIR through preprocess -> train -> bundle -> verify
    as Ray tasks, captures side by side across the cluster.

    A capture is static or dynamic by the "kind" in its object.json, else by --kind. Run it again
    to resume: a capture whose bundle verifies is skipped, a stage whose output is complete is not
    redone (--force redoes all). Exit 0: every capture succeeded (or was done); 1: some failed
    (named at the end, each with its error in OUT/summary.json); 2: bad arguments.
    """
    from dbb_capture.batch.config import BatchConfig, DynamicSettings, StaticSettings
    from dbb_capture.batch.run import run_batch
    from dbb_capture.core.progress import console

    base = BatchConfig()

    def pre(p):
        return replace(p, background=replace(p.background, minutes=background_minutes, steps=background_steps))

    cfg = BatchConfig(
        static=StaticSettings(preprocess=pre(base.static.preprocess),
                              run=replace(base.static.run, minutes=None if static_steps else static_minutes,
                                          steps=static_steps)),
        dynamic=DynamicSettings(preprocess=pre(base.dynamic.preprocess), model=base.dynamic.model,
                                train=replace(base.dynamic.train, minutes=None if dynamic_steps else dynamic_minutes,
                                              steps=dynamic_steps)),
        default_kind=default_kind, retries=retries, gpus_per_train=gpus_per_train,
        preprocess_cpus=float(preprocess_cpus), force=force)
    summary = run_batch(captures_dir, out, cfg, address)
    console.print(f"summary: {out / 'summary.json'}", soft_wrap=True)
    if summary.failed:
        console.print("[red]failed:[/red] " + ", ".join(c.name for c in summary.failed), soft_wrap=True)
        return 1
    return 0
