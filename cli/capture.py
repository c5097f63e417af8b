"""``dbb-capture``: synthetic captures, calibration and preprocessing."""

from __future__ import annotations

import json
from pathlib import Path

import click

from rich.markup import escape

from dbb_capture.core.progress import console

from .common import DbbGroup, given, overwrite_option, refuse_with


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
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
    from dbb_capture.capture.board import BoardSpec
    from dbb_capture.synth.capture import write_capture
    from dbb_capture.synth.scene import SynthConfig

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
    console.print(f"[green]wrote[/green] {escape(str(made.root))}: {made.n_frames} frames "
                  f"({made.width}x{made.height} @ {made.fps:g} fps), "
                  f"{made.n_background_frames} clean-plate frames, "
                  f"{made.seconds_per_frame * 1000:.0f} ms/frame")


def _workers(value: int | None) -> int:
    import os

    return value if value else max(1, min(2, os.cpu_count() or 1))


@main.command()
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@click.option("--board", "board_path", type=click.Path(path_type=Path), default=None,
              help="board.json (default: INPUT/board.json when INPUT is a capture folder).")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="camera.json to write.")
@click.option("--fps", type=click.FloatRange(min=0.01), default=None,
              help="Sample the footage at this rate (default: every frame).")
@click.option("--max-views", type=click.IntRange(3, 500), default=40, show_default=True,
              help="Most board views used (the most diverse are chosen).")
@click.option("--workers", type=click.IntRange(1, 64), default=None,
              help="Processes decoding and detecting (default: up to 2).")
@click.option("--precise", is_flag=True,
              help="Saddle-point corners, off-pose corners dropped, square pixels unless the corners "
                   "call for two focal lengths (default: OpenCV's own calibration).")
@overwrite_option
def calibrate(input_path: Path, board_path: Path | None, output: Path, fps: float | None,
              max_views: int, workers: int | None, precise: bool, overwrite: bool) -> None:
    """Calibrate camera intrinsics from board footage INPUT.

    INPUT is a video file, a folder of images or RAW files, a Record3D .r3d export, or a
    capture folder. Writes camera.json with the reprojection RMS as "rms". By default the
    result is OpenCV's calibration of the same corners; --precise is more accurate from many
    views (see docs/commands/calibrate.md).
    """
    from dbb_capture.capture.board import BoardSpec
    from dbb_capture.capture.footage import open_footage
    from dbb_capture.core.errors import DbbError
    from dbb_capture.core.outputs import check_writable, write_json
    from dbb_capture.core.progress import progress
    from dbb_capture.poses.calibrate import calibrate_footage

    if output.exists() and not overwrite:
        raise DbbError(f"{output} already exists (pass --overwrite to replace it)")
    # The footage first: a missing or unreadable INPUT is named before the board it would hold.
    source = open_footage(input_path)
    source.info  # probe now: unreadable footage fails before any progress bar is drawn
    if board_path is None:
        if not (input_path.is_dir() and (input_path / "board.json").is_file()):
            raise click.BadParameter("pass --board board.json (INPUT holds no board.json)")
        board_path = input_path / "board.json"
    board = BoardSpec.load(board_path)
    check_writable(output)
    with progress(transient=True) as prog:
        task = prog.add_task("detect board", total=None, info="")
        cal = calibrate_footage(source, board, fps, max_views, workers=_workers(workers),
                                tick=lambda n: prog.advance(task, n),
                                total=lambda n: prog.update(task, total=n), precise=precise)
    write_json(output, cal.to_json())
    i = cal.intrinsics
    console.print(f"[green]wrote[/green] {escape(str(output))}: fx {i.fx:.2f} fy {i.fy:.2f} cx {i.cx:.2f} "
                  f"cy {i.cy:.2f}, RMS {cal.rms:.3f} px over {len(cal.used)} views"
                  + (f" ({len(cal.rejected)} outlier views rejected)" if cal.rejected else ""))


# Options read only from a stage on: with --stop-after before it they would do nothing.
_READ_FROM = {"background": ("background", "background_minutes", "background_steps", "clean_plate", "video_room",
                             "crop_size", "max_crop_size", "crop_fill"),
              "crops": ("test_fraction", "sequence_length")}
# What a fixed camera (--crop-window) has none of: board, poses, a room field.
_NOT_FIXED = ("board_path", "camera_path", "object_path", "refine", "blur_ratio", "background_minutes",
              "background_steps", "clean_plate", "video_room", "stop_after", "max_crop_size")


def _refuse_contradictions(fixed: bool, stop_after: str | None) -> None:
    """Options that contradict each other, or do nothing with the others given, are refused
    before any work (one line naming them)."""
    if fixed:
        refuse_with(given(*_NOT_FIXED), "not used with --crop-window (a fixed camera: no board, poses or "
                                        "room field; the crops come from the window)")
    else:
        refuse_with(given("fixed_matte"), "applies with --crop-window only (the board's crops are always matted)")
    later = {"poses": ("background", "crops"), "background": ("crops",)}.get(stop_after or "", ())
    if later:
        names = [n for s in later for n in _READ_FROM[s]]
        refuse_with(given(*names), f"not used with --stop-after {stop_after} (the {' and '.join(later)} "
                                   f"stage{'s do' if len(later) > 1 else ' does'} not run)")
    if len(given("background_minutes", "background_steps")) == 2:
        raise click.UsageError("--background-minutes and --background-steps are two budgets for the room "
                               "field: give one")
    if given("background") and given("clean_plate") == ["--no-clean-plate"]:
        raise click.UsageError("--background gives a clean plate and --no-clean-plate says not to use one: "
                               "give one of them")
    if given("clean_plate") == ["--no-clean-plate"] and given("video_room"):
        raise click.UsageError(f"{given('video_room')[0]} applies with a clean plate only; --no-clean-plate "
                               "learns the room from the object video")


@main.command()
@click.argument("capture", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="Dataset folder to write.")
@click.option("--board", "board_path", type=click.Path(path_type=Path), default=None,
              help="board.json (default: CAPTURE/board.json).")
@click.option("--camera", "camera_path", type=click.Path(path_type=Path), default=None,
              help="camera.json (default: CAPTURE/camera.json, else calibrated).")
@click.option("--footage", type=click.Path(path_type=Path), default=None,
              help="Video, frames/RAW folder or .r3d (default: in CAPTURE).")
@click.option("--object", "object_path", type=click.Path(path_type=Path), default=None,
              help="object.json (default: CAPTURE/object.json).")
@click.option("--background", type=click.Path(path_type=Path), default=None,
              help="Clean plate (default: CAPTURE/background.mp4 or background/).")
@click.option("--fps", type=click.FloatRange(min=0.01), default=None,
              help="Sample the footage at this rate (default: every frame).")
@click.option("--blur-ratio", type=click.FloatRange(0, 1), default=0.4, show_default=True, metavar="R",
              help="Drop frames less sharp than this share of their neighbours' (0: keep all).")
@click.option("--refine/--no-refine", default=False, show_default=True,
              help="Refine intrinsics and poses jointly (bundle adjustment).")
@click.option("--crop-size", type=int, default=None,
              help="Crop side in pixels (default: as fine as the footage for a static object, 64 for a "
                   "dynamic one).")
@click.option("--max-crop-size", type=click.IntRange(32, 1024), default=512, show_default=True,
              help="Largest crop side chosen from the footage.")
@click.option("--crop-fill", type=float, default=0.9, show_default=True,
              help="Share of the crop side the object's sphere spans.")
@click.option("--test-fraction", type=float, default=0.2, show_default=True,
              help="The last share of the capture's time held out as test.")
@click.option("--sequence-length", type=int, default=11, show_default=True,
              help="Frames per RSSM window (1 context + N-1 predicted).")
@click.option("--background-minutes", type=click.FloatRange(min=0.05), default=2.0, show_default=True, metavar="M",
              help="Training budget of the room field.")
@click.option("--background-steps", type=click.IntRange(min=1), default=None, metavar="N",
              help="Steps instead of minutes (reproducible).")
@click.option("--clean-plate/--no-clean-plate", default=True, show_default=True,
              help="Learn the room from the clean plate.")
@click.option("--video-room/--no-video-room", default=True, show_default=True,
              help="With a plate: also from the video's rays past the object.")
@click.option("--crop-window", type=str, default=None, metavar="X,Y,SIZE",
              help="Fixed camera, no board: crop this window (top-left, side; pixels).")
@click.option("--matte/--no-matte", "fixed_matte", default=True, show_default=True,
              help="With --crop-window: matte the crops (off: opaque).")
@click.option("--stop-after", type=str, default=None,
              help="Stop after this stage: poses, background or crops.")
@click.option("--workers", type=click.IntRange(1, 64), default=None,
              help="Processes decoding and detecting (default: up to 2).")
@overwrite_option
def preprocess(capture: Path, output: Path, board_path: Path | None, camera_path: Path | None,
               footage: Path | None, object_path: Path | None, background: Path | None,
               fps: float | None, blur_ratio: float, refine: bool, crop_size: int | None, max_crop_size: int,
               crop_fill: float,
               test_fraction: float, sequence_length: int, background_minutes: float, background_steps: int | None,
               clean_plate: bool, video_room: bool,
               crop_window: str | None, fixed_matte: bool, stop_after: str | None, workers: int | None, overwrite: bool) -> None:
    """Turn CAPTURE into a dataset: poses, room field, mattes and RGBA crops.

    Writes images/, transforms.json, masks/, camera.json, colmap/, poses/, background/,
    crops/, crops.json, dataset.json and contact_sheet.png (docs/commands/preprocess.md).
    """
    from dataclasses import replace

    from dbb_capture.background.config import BackgroundConfig
    from dbb_capture.preprocess.inputs import PreprocessConfig, resolve_capture
    from dbb_capture.preprocess.run import run_preprocess

    window = None
    if crop_window is not None:
        try:
            window = tuple(int(v) for v in crop_window.split(","))
            assert len(window) == 3
        except (ValueError, AssertionError):
            raise click.BadParameter("expected X,Y,SIZE in pixels, e.g. 200,40,280",
                                     param_hint="--crop-window") from None
    _refuse_contradictions(window is not None, stop_after)
    inputs = resolve_capture(capture, board_path, camera_path, footage, object_path, background,
                             need_board=window is None)
    cfg = PreprocessConfig(fps=fps, blur_ratio=blur_ratio, refine=refine, crop_window=window, fixed_matte=fixed_matte,
                           workers=_workers(workers), stop_after=stop_after, crop_size=crop_size,
                           max_crop_size=max_crop_size, crop_fill=crop_fill, test_fraction=test_fraction, sequence_length=sequence_length,
                           use_clean_plate=clean_plate,
                           background=replace(BackgroundConfig(), minutes=background_minutes, steps=background_steps,
                                              video_room=video_room))
    res = run_preprocess(inputs, output, cfg, overwrite=overwrite)
    for warning in res.warnings:
        console.print(f"[yellow]warning:[/yellow] {escape(warning)}", soft_wrap=True)
    for note in res.notes:
        console.print(f"[yellow]note:[/yellow] {escape(note)}", soft_wrap=True)
    last = res.stages_run[-1] if res.stages_run else None
    what = ""
    if last == "poses":
        what = f"; {len(res.last.images)} posed frames"
    elif last in ("crops", "fixed camera"):
        st = res.last.stats
        what = (f"; {st['crops']} crops ({st['train']} train, {st['test']} test), "
                f"{st['sequences']['train']} + {st['sequences']['test']} sequences; see dataset.json "
                f"and contact_sheet.png")
    console.print(f"[green]wrote[/green] {escape(str(res.dataset))}: stages {', '.join(res.stages_run)}" + what)
    poses = Path(res.dataset) / "poses" / "report.json"
    report = json.loads(poses.read_text()) if poses.is_file() else {}
    if "frames_posed" in report:              # a fixed camera has no poses to speak of
        console.print(_poses_words(report), markup=False)


def _poses_words(report: dict) -> str:
    """What the poses stage's figures mean, in one line."""
    err = report.get("reprojection_px") or {}
    line = f"poses: {report['frames_posed']} of {report['frames_sampled']} frames posed"
    if "median" in err:
        line += (f", the board's corners land {err['median']:.2f} px (median; 95 % within {err['p95']:.2f} px) "
                 "from where the poses and lens put them (under 1 px is good)")
    return line + "; camera centres and object sphere in poses/camera_path.png"
