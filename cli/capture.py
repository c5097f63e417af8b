"""``dbb-capture``: synthetic captures, calibration and preprocessing."""

from __future__ import annotations

from pathlib import Path

import click

from dbb_capture.progress import console

from .common import DbbGroup, overwrite_option


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="dbb-capture")
def main() -> None:
    """Capture stage: make synthetic captures, calibrate cameras, preprocess footage."""


def _floats(text: str | None, n: int | None, what: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise click.BadParameter(f"{what}: expected numbers, got {text!r}") from None
    if n is not None and len(vals) != n:
        raise click.BadParameter(f"{what}: expected {n} numbers, got {len(vals)}")
    return vals


@main.command()
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--kind", type=click.Choice(["static", "dynamic"]), required=True,
              help="static: a rigid object; dynamic: parts move on their own.")
@click.option("--seconds", type=click.FloatRange(min=0.1), default=10.0, show_default=True,
              help="Length of the object video.")
@click.option("--background-seconds", type=click.FloatRange(min=0.1), default=None,
              help="Length of the clean plate (default: same as --seconds).")
@click.option("--fps", type=click.FloatRange(min=1, max=120), default=10.0, show_default=True)
@click.option("--resolution", default="640x480", show_default=True, help="WIDTHxHEIGHT in pixels.")
@click.option("--fov", type=click.FloatRange(20, 120), default=62.0, show_default=True,
              help="Horizontal field of view in degrees.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--distortion", default=None,
              help="OpenCV distortion 'k1,k2,p1,p2,k3' (default: none).")
@click.option("--board-squares", default="7x5", show_default=True, help="SQUARES_XxSQUARES_Y.")
@click.option("--square-length", type=click.FloatRange(min=0.001), default=0.05, show_default=True,
              help="Square side in metres.")
@click.option("--marker-length", type=click.FloatRange(min=0.001), default=0.0375, show_default=True,
              help="Marker side in metres.")
@click.option("--dictionary", default="DICT_5X5_100", show_default=True,
              help="OpenCV ArUco dictionary name.")
@click.option("--legacy-pattern", is_flag=True, help="Board drawn with OpenCV < 4.6's pattern.")
@click.option("--samples", type=click.IntRange(2, 6), default=2, show_default=True,
              help="Anti-aliasing samples per pixel along each axis.")
@click.option("--noise", type=click.FloatRange(0, 0.2), default=0.01, show_default=True,
              help="Sensor read-noise std (fraction of full scale); shot noise scales with it.")
@click.option("--crf", type=click.IntRange(0, 51), default=18, show_default=True,
              help="H.264 quality of the videos (lower: better and larger).")
@click.option("--camera-json", is_flag=True,
              help="Also write camera.json (true intrinsics) so preprocess skips calibration.")
@click.option("--no-background", is_flag=True, help="Do not write a clean plate.")
@overwrite_option
def synth(out: Path, kind: str, seconds: float, background_seconds: float | None, fps: float,
          resolution: str, fov: float, seed: int, distortion: str | None, board_squares: str,
          square_length: float, marker_length: float, dictionary: str, legacy_pattern: bool,
          samples: int, noise: float, crf: int, camera_json: bool, no_background: bool,
          overwrite: bool) -> None:
    """Render a synthetic capture with ground truth into OUT.

    Writes video.mp4, background.mp4 (clean plate), board.json, object.json, camera.json
    and ground_truth/ (intrinsics, per-frame poses, object masks, the object's model).
    """
    from dbb_capture.board import BoardSpec
    from dbb_capture.synth import SynthConfig, write_capture

    try:
        w, h = (int(v) for v in resolution.lower().split("x"))
        sx, sy = (int(v) for v in board_squares.lower().split("x"))
    except ValueError:
        raise click.BadParameter("expected WIDTHxHEIGHT / SQUARES_XxSQUARES_Y, e.g. 640x480") from None
    if w < 64 or h < 64:
        raise click.BadParameter(f"--resolution {resolution}: at least 64x64")
    board = BoardSpec(sx, sy, square_length, marker_length, dictionary, legacy_pattern)
    cfg = SynthConfig(
        kind=kind, seconds=seconds, fps=fps, width=w, height=h, hfov_deg=fov, seed=seed,
        dist=_floats(distortion, 5, "--distortion") or (0.0,) * 5, board=board,
        samples=samples, noise=noise, crf=crf,
        background_seconds=None if no_background else (background_seconds or seconds))
    made = write_capture(cfg, out, overwrite=overwrite, with_camera_json=camera_json)
    console.print(f"[green]wrote[/green] {made.root}: {made.n_frames} frames "
                  f"({made.width}x{made.height} @ {made.fps:g} fps), "
                  f"{made.n_background_frames} clean-plate frames, "
                  f"{made.seconds_per_frame * 1000:.0f} ms/frame")
