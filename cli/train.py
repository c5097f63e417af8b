"""``dbb-train``: fit a billboard model to a preprocessed dataset."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import click

from .common import DbbGroup


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="dbb-capture")
def main() -> None:
    """Training stage: static objects (PlenOctree) and dynamic objects (RSSM)."""


@main.command("plenoctree")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Run folder to write (tree.npz, run.json, density_grid.npz, report/).")
@click.option("--minutes", type=float, default=None,
              help="Wall-clock training budget; the coarse-to-fine schedule adapts to it (default 10).")
@click.option("--steps", type=int, default=None, help="Stop after this many steps (first limit wins).")
@click.option("--downscale", type=float, default=1.0, show_default=True, help="Train on images shrunk by this factor.")
@click.option("--resume", is_flag=True, help="Continue from the run's last checkpoint.")
@click.option("--overwrite", is_flag=True, help="Replace the run folder if it exists.")
@click.option("--mode", type=click.Choice(["auto", "object", "scene"]), default="auto", show_default=True,
              help="object: bounded, RGBA supervision; scene: unbounded (contracted); auto: object if images have alpha.")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=2, show_default=True)
@click.option("--sh-full-from", type=click.FloatRange(0, 1), default=0.8, show_default=True,
              help="Fraction of the budget from which the SH bands above degree 1 train (progressive SH; "
                   "before it the colour is degree 1, which steps faster and extrapolates better; "
                   "0: all from the start).")
@click.option("--res-max", type=click.IntRange(16, 512), default=None,
              help="Finest lattice per axis inside the object's cube (default: one cell per pixel, the next "
                   "power of two at or above the pixels the training views span across the object, 32-512).")
@click.option("--max-points", type=int, default=6_000_000, show_default=True,
              help="Do not refine past this many active lattice points (memory and time on CPU).")
@click.option("--depth", type=click.IntRange(1, 8), default=None, help="Octree depth (default: match the lattice).")
@click.option("--prune-weight", type=click.FloatRange(0, 1), default=0.005, show_default=True,
              help="Bake drops octree leaves that no training ray gives this rendering weight (0: keep all).")
@click.option("--holdout-every", type=int, default=8, show_default=True,
              help="Without a split in the dataset, every n-th frame is held out for the report (0: none).")
@click.option("--holdout", "holdout_names", default="", help="Comma-separated frame names (file stems) to hold out.")
@click.option("--batch-rays", type=int, default=4096, show_default=True)
@click.option("--robust-from", type=click.FloatRange(0, 1), default=None,
              help="From this fraction of the budget, rays whose error stays large lose weight (Cauchy IRLS), "
                   "so the views outvote a matte's errors (1: off; default 0.5 on preprocess crops, else off).")
@click.option("--carve", "carve_share", type=click.FloatRange(0, 1), default=None,
              help="Leave out space that at least this share of the views that see it see as clearly empty "
                   "(0: off; default 0.1 on preprocess crops, else off).")
@click.option("--observed/--no-observed", "observed_loss", default=None,
              help="Preprocess crops: render over the predicted room and compare with the observed pixel where "
                   "its colour decides (the matte elsewhere), so a part a matte missed is kept by the views "
                   "that see it (default on for preprocess crops; other datasets have no observed pixels).")
@click.option("--threads", type=click.IntRange(1, 256), default=None,
              help="CPU threads (default: torch's choice; on a machine shared with other jobs 1 is faster).")
def plenoctree(dataset, out, minutes, steps, downscale, resume, overwrite, mode, sh_degree, sh_full_from, res_max,
               max_points, depth, prune_weight, holdout_every, holdout_names, batch_rays, robust_from, carve_share,
               observed_loss, threads) -> None:
    """Static object: train a voxel radiance field on DATASET and bake it into a PlenOctree.

    DATASET is a preprocess output (crops.json) or a nerfstudio / instant-ngp / Blender
    dataset folder or json file.
    """
    from dbb_capture.static.field import FieldConfig
    from dbb_capture.static.run import RunConfig, train_run
    from dbb_capture.core.progress import console

    if threads:
        import torch

        torch.set_num_threads(threads)
    names = tuple(n.strip() for n in holdout_names.split(",") if n.strip())
    cfg = RunConfig(minutes, steps, downscale, mode, holdout_every, names, depth, prune_weight)
    fcfg = FieldConfig(sh_degree=sh_degree, sh_full_from=sh_full_from, res_max=res_max, max_points=max_points,
                       batch_rays=batch_rays, res_start=min(32, res_max or 32), robust_from=robust_from,
                       carve_share=carve_share,
                       observed_loss=observed_loss)
    run = train_run(dataset, out, cfg, fcfg, resume=resume, overwrite=overwrite)
    m = run.meta
    mp = m["metrics"].get("mean_psnr_tree_white")
    console.print(f"wrote {out}: tree.npz ({m['tree']['bytes'] / 1e6:.1f} MB, {m['tree']['data_format']}, "
                  f"depth {m['tree']['depth_limit']}), {m['training']['steps']} steps in "
                  f"{m['training']['seconds'] / 60:.1f} min"
                  + (f", {m['metrics']['views']} PSNR {mp:.2f} dB on white" if mp is not None else ""))


@main.command("rssm")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Run folder to write (run.json, model.pt, stepper.ts, checkpoint.pt, report/).")
@click.option("--minutes", type=float, default=None, help="Wall-clock training budget (default 15).")
@click.option("--steps", type=int, default=None, help="Stop after this many steps (first limit wins).")
@click.option("--size", type=click.Choice(["32", "64", "128", "256"]), default="64", show_default=True,
              help="Frame side in pixels (crops are resized to it).")
@click.option("--batch", type=click.IntRange(1, 512), default=8, show_default=True, help="Sequences per step.")
@click.option("--threads", type=click.IntRange(1, 256), default=None,
              help="CPU threads for torch (default: torch's choice).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--temperature", type=click.FloatRange(0.0, 10.0), default=None,
              help="Run-time sampling temperature of the stochastic state (0: its mean, which shrinks motion). "
                   "Default: fitted to the footage, so that at a still viewpoint the rollouts move as much as "
                   "the object does in the footage (run.json: stepper.temperature_calibration).")
@click.option("--resume", is_flag=True,
              help="Continue from the run's last checkpoint, with its model and training settings (training "
                   "settings, --batch and --seed given here override them; --minutes/--steps count in all).")
@click.option("--overwrite", is_flag=True, help="Replace the run folder if it exists.")
@click.option("--set", "settings", multiple=True, metavar="NAME=VALUE",
              help="A model or training setting other than its default, e.g. compose=accum (repeatable; "
                   "docs/commands/rssm.md lists them).")
@click.option("--preset", type=click.Choice(["swing"]), default=None,
              help="A named bundle of settings, applied before --set: 'swing' for a small part that swings "
                   "in front of a still camera (a pendulum; docs/commands/rssm.md).")
def rssm(dataset, out, minutes, steps, size, batch, threads, seed, temperature, resume, overwrite, settings,
         preset) -> None:
    """Dynamic object: train a viewpoint-conditioned RSSM video predictor on DATASET (crops.json).

    Writes the weights, a TorchScript stepper and the evaluation (per-step PSNR/SSIM of 10-step
    open-loop predictions vs the "near" and copy-first-frame baselines, motion-energy ratio of
    150-step rollouts at a still viewpoint) into the run folder.
    """
    import torch

    from dbb_capture.dynamic.rssm import RssmConfig, TrainConfig, configs_from_settings, resume_configs, train_run

    if threads:
        torch.set_num_threads(threads)
    pairs = ([f"preset={preset}"] if preset else []) + list(settings)
    if resume:      # the run's own settings, under what this command says (the model stays the checkpoint's)
        ctx = click.get_current_context()
        given = {k: v for k, v in (("batch", batch), ("seed", seed))
                 if ctx.get_parameter_source(k) is not click.core.ParameterSource.DEFAULT}
        cfg, tcfg = resume_configs(out)
        tcfg = replace(tcfg, minutes=minutes, steps=steps, **given)
    else:
        cfg, tcfg = RssmConfig(size=int(size)), TrainConfig(minutes, steps, batch=batch, seed=seed)
    cfg, tcfg = configs_from_settings(pairs, cfg, tcfg)
    meta = train_run(dataset, out, cfg, tcfg, resume=resume, overwrite=overwrite, temperature=temperature)
    _print_rssm(out, meta["eval"], f"{meta['training']['steps']} steps in {meta['training']['seconds'] / 60:.1f} min")


@main.command("rssm-eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="Evaluate on this crops.json dataset instead of the run's own.")
@click.option("--temperature", type=click.FloatRange(0.0, 10.0), default=None,
              help="New run-time sampling temperature (also rewrites stepper.ts and run.json's stepper entry).")
@click.option("--calibrate", is_flag=True,
              help="Fit the run-time temperature to the footage again (as training does by default).")
def rssm_eval(run, dataset, temperature, calibrate) -> None:
    """Re-run the evaluation of an RSSM RUN folder (rewrites RUN/report/ and run.json's eval)."""
    from dbb_capture.dynamic.rssm import eval_run

    if calibrate and temperature is not None:
        raise click.UsageError("give --temperature or --calibrate, not both")
    _print_rssm(run, eval_run(run, dataset, temperature, calibrate=calibrate).to_json(), "re-evaluated")


def _print_rssm(out: Path, ev: dict, what: str) -> None:
    from dbb_capture.core.progress import console

    p = ev["mean_psnr_db"]
    console.print(f"wrote {out}: {what}; 10-step open-loop PSNR {p['model']:.2f} dB "
                  f"(copy-first {p['copy_first']:.2f}, near {p['near']:.2f}) on {ev['windows']} {ev['split']} "
                  f"windows; motion-energy ratio {ev['motion']['ratio']}")
    st = json.loads((Path(out) / "run.json").read_text())["stepper"]
    cal = st.get("temperature_calibration")
    console.print(f"run-time temperature {st['temperature']:.3g}"
                  + ("" if cal is None else " (fitted to the footage's still-view motion"
                     + (f"; {cal['note']}" if cal.get("note") else "") + ")"))
