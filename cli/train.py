"""``dbb-train``: fit a billboard model to a preprocessed dataset."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click
from rich.markup import escape

from dbb_capture.dynamic.config import preset_names

from .common import DbbGroup, refuse_resume_overwrite, typed


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="dbb-capture")
def main() -> None:
    """Training stage: static objects (PlenOctree) and dynamic objects (RSSM)."""


@main.command("plenoctree")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Run folder to write (run.json, tree.npz, density_grid.npz, report/).")
@click.option("--minutes", type=float, default=None, help="Wall-clock training budget (default 10).")
@click.option("--steps", type=int, default=None, help="Stop after this many steps (first limit wins).")
@click.option("--downscale", type=click.FloatRange(min=1.0), default=1.0, show_default=True,
              help="Train on images shrunk by this factor.")
@click.option("--resume", is_flag=True, help="Continue from the run's last checkpoint.")
@click.option("--overwrite", is_flag=True, help="Replace the run folder if it exists.")
@click.option("--mode", type=click.Choice(["auto", "object", "scene"]), default="auto", show_default=True,
              help="object: bounded, RGBA; scene: unbounded; auto: object if the images have alpha.")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=2, show_default=True)
@click.option("--sh-full-from", type=click.FloatRange(0, 1), default=0.8, show_default=True,
              help="Budget share from which SH bands above degree 1 train (0: from the start).")
@click.option("--res-max", type=click.IntRange(16, 512), default=None,
              help="Finest lattice per axis (default: one cell per training pixel, 32-512).")
@click.option("--max-points", type=int, default=6_000_000, show_default=True,
              help="Do not refine past this many active lattice points.")
@click.option("--depth", type=click.IntRange(1, 8), default=None, help="Octree depth (default: the lattice's).")
@click.option("--prune-weight", type=click.FloatRange(0, 1), default=0.005, show_default=True,
              help="Drop octree leaves no training ray weights this much (a depth-7 leaf's; halved per level deeper; 0: keep all).")
@click.option("--holdout-every", type=int, default=8, show_default=True,
              help="Without a split, hold out every n-th frame (0: none).")
@click.option("--holdout", "holdout_names", default="", help="Comma-separated frame names to hold out instead.")
@click.option("--batch-rays", type=int, default=4096, show_default=True)
@click.option("--robust-from", type=click.FloatRange(0, 1), default=None,
              help="Budget share from which rays that keep disagreeing lose weight (1: off; crops: 0.5).")
@click.option("--carve", "carve_share", type=click.FloatRange(0, 1), default=None,
              help="Remove space this share of the views see through (0: off; crops: 0.1).")
@click.option("--observed/--no-observed", "observed_loss", default=None,
              help="Compare with the observed pixels over the predicted room (crops: on).")
@click.option("--threads", type=click.IntRange(1, 256), default=None,
              help="torch's CPU threads (1 is faster on a shared machine).")
def plenoctree(dataset, out, minutes, steps, downscale, resume, overwrite, mode, sh_degree, sh_full_from, res_max,
               max_points, depth, prune_weight, holdout_every, holdout_names, batch_rays, robust_from, carve_share,
               observed_loss, threads) -> None:
    """Static object: train a voxel radiance field on DATASET and bake it into a PlenOctree.

    DATASET is a preprocess output (crops.json) or a nerfstudio / instant-ngp / Blender
    dataset folder or json file.
    """
    from dbb_capture.core.progress import console
    from dbb_capture.static.field import FieldConfig
    from dbb_capture.static.run import RunConfig, train_run

    refuse_resume_overwrite(resume, overwrite)
    if threads:
        import torch

        torch.set_num_threads(threads)
    names = tuple(n.strip() for n in holdout_names.split(",") if n.strip())
    cfg = RunConfig(minutes, steps, downscale, mode, holdout_every, names, depth, prune_weight)
    fcfg = FieldConfig(sh_degree=sh_degree, sh_full_from=sh_full_from, res_max=res_max, max_points=max_points,
                       batch_rays=batch_rays, res_start=min(32, res_max or 32), robust_from=robust_from,
                       carve_share=carve_share,
                       observed_loss=observed_loss)
    # A resumed run trains its checkpoint's field: these options, typed, must agree with it.
    asked = typed("mode", "sh_degree", "sh_full_from", "res_max", "max_points", "batch_rays", "robust_from",
                  "carve_share", "observed_loss")
    run = train_run(dataset, out, cfg, fcfg, resume=resume, overwrite=overwrite, resume_asks=tuple(asked))
    rec = run.record
    sets = rec.metrics.get("sets", {})
    console.print(f"wrote {escape(str(out))}: {rec.tree.file} ({rec.tree.bytes / 1e6:.1f} MB, {rec.tree.data_format}, "
                  f"depth {rec.tree.depth_limit}, {rec.final_res}^3 lattice), {rec.training.steps} steps in "
                  f"{rec.training.seconds / 60:.1f} min")
    for name, st in sets.items():
        console.print(_psnr_words(name, st, out), markup=False)


@main.command("rssm")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Run folder to write (run.json, model.pt, stepper.ts, checkpoint.pt, report/).")
@click.option("--minutes", type=float, default=None, help="Training budget in minutes (default 15).")
@click.option("--steps", type=int, default=None, help="Stop after this many steps (first limit wins).")
@click.option("--size", type=click.Choice(["32", "64", "128", "256"]), default="64", show_default=True,
              help="Frame side in pixels (crops are resized to it).")
@click.option("--batch", type=click.IntRange(1, 512), default=8, show_default=True, help="Sequences per step.")
@click.option("--threads", type=click.IntRange(1, 256), default=None,
              help="CPU threads for torch (default: torch's choice).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--temperature", type=click.FloatRange(0.0, 10.0), default=None,
              help="Run-time sampling temperature of the stochastic state (0: its mean). Default: fitted "
                   "to the footage's motion at a still viewpoint (run.json: stepper.temperature_calibration).")
@click.option("--resume", is_flag=True,
              help="Continue from the run's last checkpoint with its settings (--set, --batch and --seed "
                   "given here override them; --minutes/--steps count in all).")
@click.option("--overwrite", is_flag=True, help="Replace the run folder if it exists.")
@click.option("--preset", type=click.Choice(preset_names()), default=None,
              help="Settings for a kind of footage, applied before --set: 'swing' for a small part that "
                   "swings in front of a still camera (dbb_capture/dynamic/presets/).")
@click.option("--set", "settings", multiple=True, metavar="NAME=VALUE",
              help="A model, loss or training setting other than its default, e.g. loss_scales.energy=100 "
                   "(repeatable; docs/commands/rssm.md lists them).")
def rssm(dataset, out, minutes, steps, size, batch, threads, seed, temperature, resume, overwrite, preset,
         settings) -> None:
    """Dynamic object: train a viewpoint-conditioned RSSM video predictor on DATASET (crops.json).

    Writes the weights, a TorchScript stepper and the evaluation (per-step PSNR/SSIM of 10-step
    open-loop predictions vs the "near" and copy-first-frame baselines, motion-energy ratio of
    150-step rollouts at a still viewpoint) into the run folder.
    """
    import torch

    from dbb_capture.core.errors import DbbError
    from dbb_capture.dynamic.config import (
        RssmConfig,
        TrainConfig,
        apply_preset,
        configs_from_settings,
        model_changes,
    )
    from dbb_capture.dynamic.run import resume_configs, train_run

    refuse_resume_overwrite(resume, overwrite)
    if threads:
        torch.set_num_threads(threads)
    if resume:      # the run's own settings, under what this command says (the model stays the checkpoint's)
        ctx = click.get_current_context()
        given = {k: v for k, v in (("batch", batch), ("seed", seed))
                 if ctx.get_parameter_source(k) is not click.core.ParameterSource.DEFAULT}
        run_cfg, tcfg = resume_configs(out)
        cfg = replace(run_cfg, size=int(size)) if ctx.get_parameter_source("size") is not \
            click.core.ParameterSource.DEFAULT else run_cfg
        tcfg = replace(tcfg, minutes=minutes, steps=steps, **given)
    else:
        cfg, tcfg = RssmConfig(size=int(size)), TrainConfig(minutes, steps, batch=batch, seed=seed)
    if preset:
        cfg, tcfg = apply_preset(preset, cfg, tcfg)
    try:
        cfg, tcfg = configs_from_settings(list(settings), cfg, tcfg)
    except DbbError as e:
        raise DbbError(f"--set {e}") from None
    changed = model_changes(run_cfg, cfg) if resume else []
    if changed:
        raise click.UsageError(f"--resume keeps the run's model, and these settings differ from it: "
                               f"{'; '.join(changed)}; drop them or train a new run")
    record = train_run(dataset, out, cfg, tcfg, resume=resume, overwrite=overwrite, temperature=temperature)
    _print_rssm(out, record, f"{record.training.steps} steps in {record.training.seconds / 60:.1f} min")


@main.command("rssm-eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="Evaluate on this crops.json dataset instead of the run's own.")
@click.option("--temperature", type=click.FloatRange(0.0, 10.0), default=None,
              help="New run-time sampling temperature (also rewrites stepper.ts and run.json's stepper entry).")
@click.option("--calibrate", is_flag=True,
              help="Fit the run-time temperature (and an oscillator cell's bound) to the footage again, as training does.")
def rssm_eval(run, dataset, temperature, calibrate) -> None:
    """Re-run the evaluation of an RSSM RUN folder (rewrites RUN/report/ and run.json's eval)."""
    from dbb_capture.dynamic.record import RunRecord
    from dbb_capture.dynamic.run import eval_run

    if calibrate and temperature is not None:
        raise click.UsageError("give --temperature or --calibrate, not both")
    eval_run(run, dataset, temperature, calibrate=calibrate)
    _print_rssm(run, RunRecord.read(run), "re-evaluated")


def _psnr_words(name: str, st: dict, out: Path) -> str:
    """What a PlenOctree run's PSNR on one set of views (``name``, its metrics ``st``) means, in one line."""
    from dbb_capture.core.metrics import rms_levels

    p = st["mean_psnr_tree_white"]
    which = (f"{st['views']} {name} held-out views ({st['what']})" if name != "training"
             else "training views (no held-out ones: fit, not new views)")
    return (f"PSNR {p:.1f} dB on {which}: renders differ from the photos by {rms_levels(p):.1f} of 255 levels "
            f"(RMS, white background included); higher is better, 30 dB and up usually looks close to the "
            f"photo; truth | render in {out / 'report'}/heldout_*.png")


def _rssm_words(ev: dict, out: Path) -> str:
    """What an RSSM run's evaluation means, in one line."""
    p = ev["mean_psnr_db"]
    gain = {"vs_copy_first": p["model"] - p["copy_first"], "vs_near": p["model"] - p["near"]}
    ratio = ev["motion"]["ratio"]
    motion = ("the footage does not move at a still viewpoint (no motion ratio)" if ratio is None else
              f"rollouts at a still viewpoint move {ratio:.2f}x as much as the footage (1 is right, 0 frozen)")
    return (f"the model predicts {gain['vs_copy_first']:+.2f} dB against copying the first frame and "
            f"{gain['vs_near']:+.2f} dB against the nearest training view (above 0: better than that baseline); "
            f"{motion}; truth / prediction / near in {out / 'report'}/strip.png")


def _print_rssm(out: Path, record, what: str) -> None:
    from dbb_capture.core.progress import console

    ev = record.eval
    p = ev["mean_psnr_db"]
    console.print(f"wrote {escape(str(out))}: {what}; 10-step open-loop PSNR {p['model']:.2f} dB "
                  f"(copy-first {p['copy_first']:.2f}, near {p['near']:.2f}) on {ev['windows']} {ev['split']} "
                  f"windows" + (f" (their views {ev['near_gap_deg']:.0f} deg from the nearest training view)"
                                if "near_gap_deg" in ev else "")
                  + f"; motion-energy ratio {ev['motion']['ratio']}")
    console.print(_rssm_words(ev, out), markup=False)
    st = record.stepper
    cal = st.temperature_calibration
    console.print(f"run-time temperature {st.temperature:.3g}"
                  + ("" if cal is None else " (fitted to the footage's still-view motion"
                     + (f"; {cal['note']}" if cal.get("note") else "") + ")")
                  + (f", reached over the first {st.warmup} steps" if st.warmup and st.temperature > 1 else ""))
