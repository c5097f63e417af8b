"""The run report's figures: ``plots.png`` (per-step PSNR/SSIM, still-view motion energy, training
losses), ``strip.png`` (a held-out window: truth / prediction / near) and ``rollout.png`` (every
10th frame of a long rollout at a still viewpoint, over its truth when known); the strips' frames
at least 256 px, rows and steps named in the image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..core.images import upscale_nearest, with_header, with_row_labels
from .evaluate import EvalReport


def write_figures(report: EvalReport, figs: dict, history: list[dict], folder: Path) -> None:
    """The three figures of ``report`` and :func:`dbb_capture.dynamic.evaluate.evaluate`'s arrays
    ``figs``, with the training ``history``, into ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    steps = np.arange(1, report.steps + 1)
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    for k in report.psnr:
        axes[0, 0].plot(steps, report.psnr[k], marker="o", label=k)
        axes[0, 1].plot(steps, report.ssim[k], marker="o", label=k)
    axes[0, 0].set(xlabel="open-loop step", ylabel="PSNR (dB)", title=f"PSNR, {report.split} split")
    axes[0, 1].set(xlabel="open-loop step", ylabel="SSIM", title=f"SSIM, {report.windows} windows")
    axes[0, 0].legend()
    ax = axes[1, 0]
    ax.plot(np.arange(1, len(figs["pred_curve"]) + 1), figs["pred_curve"], label="prediction")
    if figs["truth_curve"] is not None:
        ax.plot(np.arange(1, len(figs["truth_curve"]) + 1), figs["truth_curve"], label="truth")
    else:
        ax.axhline(figs["truth_energy"], color="k", ls="--", label="truth (dataset mean)")
    ax.set(xlabel="step", ylabel="mean |frame change|",
           title=f"motion energy at a still viewpoint, ratio {report.motion['ratio']}")
    ax.legend()
    ax = axes[1, 1]
    if history:
        s = [h["step"] for h in history]
        for k in ("rec", "kl_dyn", "kl_rep", "overshoot"):
            ax.plot(s, [max(h.get(k, 0.0), 1e-3) for h in history], label=k)
        ax.set(yscale="log")
        ax.legend()
    ax.set(xlabel="step", title="training losses")
    fig.tight_layout()
    fig.savefig(folder / "plots.png", dpi=90)
    plt.close(fig)

    # Strip: one held-out window, rows truth / model / near, on a grey checker (alpha visible).
    truth, m = figs["truth"], figs["methods"]
    steps = [f"step {k}" for k in range(1, truth.shape[1])]
    cv2.imwrite(str(folder / "strip.png"), strip_image([truth[0, 1:], m["model"][0], m["near"][0]],
                                                 ["truth", "prediction", "near (training)"], steps))
    long = figs["long"][0][::10]
    rows = [long] + ([figs["still_truth"][1::10][:len(long)]] if figs["still_truth"] is not None else [])
    cv2.imwrite(str(folder / "rollout.png"), strip_image(rows, ["prediction", "truth"][:len(rows)],
                                                   [f"step {1 + 10 * k}" for k in range(len(long))]))


FIGURE_PX = 256      # frames in the strips are shown at least this large (repeated pixels)


def strip_image(rows: list[np.ndarray], row_labels: list[str], col_labels: list[str],
          min_px: int = FIGURE_PX) -> np.ndarray:
    """Rows of premultiplied RGBA frames (n, S, S, 4) over a checkerboard, each frame enlarged to
    at least ``min_px`` (nearest), rows and columns named -> BGR uint8 image."""
    S = rows[0].shape[1]
    n = max(len(r) for r in rows)
    yy, xx = np.mgrid[:S, :S]
    bg = np.where(((yy // 8) + (xx // 8)) % 2 == 0, 0.55, 0.75)[..., None]
    out = np.ones((len(rows) * (S + 2), n * (S + 2), 3))
    for i, r in enumerate(rows):
        for j, f in enumerate(r):
            out[i * (S + 2):i * (S + 2) + S, j * (S + 2):j * (S + 2) + S] = f[..., :3] + (1 - f[..., 3:4]) * bg
    img = upscale_nearest(np.round(out[..., ::-1].clip(0, 1) * 255).astype(np.uint8), min_px, side=S)
    k = img.shape[0] // out.shape[0]
    img = with_row_labels(img, row_labels, [k * (S + 2)] * len(rows))
    return with_header(img, [""] + col_labels, [110] + [k * (S + 2)] * n)
