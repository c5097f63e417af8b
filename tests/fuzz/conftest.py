"""The fuzz suite's harness: commands run in this process (no interpreter start per case), a
time limit per case, the promise every case checks, and the valid inputs the cases corrupt
(made once per session from the shared session fixtures of ``tests/conftest.py``).

Every input lives under a folder named with square brackets and non-ASCII letters
(:data:`ODD`), so every message that names a file shows whether it prints the path whole.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from dbb_capture.cli import capture, export, train

ODD = "in [v2] tøy ü"              # a folder name rich markup would eat and ASCII would not spell
OUT = "out [x] ø"                  # where the outputs would go
CASE_SECONDS = float(os.environ.get("DBB_FUZZ_CASE_SECONDS", "45"))   # a case over this started heavy work
COMMANDS = {"dbb-capture": capture.main, "dbb-train": train.main, "dbb-export": export.main}


class CaseTimeout(BaseException):
    """A case ran past :data:`CASE_SECONDS` (BaseException: no ``except Exception`` swallows it)."""


@pytest.fixture(autouse=True)
def time_limit() -> Iterator[None]:
    """SIGALRM ends a case that runs too long: a check that comes after heavy work fails here."""
    def on_alarm(signum, frame):
        raise CaseTimeout(f"case ran over {CASE_SECONDS:g} s: a check comes after heavy work")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, CASE_SECONDS)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@dataclass(frozen=True)
class Result:
    code: int
    stderr: str
    stdout: str

    @property
    def lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]


def invoke(capfd, command: str, *args) -> Result:
    """Run ``command args`` (e.g. ``"dbb-export", "verify", path``) as its console script would,
    in this process; stdout and stderr are captured at the file descriptors, so what libraries
    print from C (libpng, FFmpeg, OpenCV) counts as it would in a terminal."""
    capfd.readouterr()
    term = signal.getsignal(signal.SIGTERM)
    try:
        COMMANDS[command].main(args=[str(a) for a in args], prog_name=command)
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        signal.signal(signal.SIGTERM, term)     # the command installs its own
    out, err = capfd.readouterr()
    if os.environ.get("FUZZ_TMP_LOG"):
        with open(os.environ["FUZZ_TMP_LOG"], "a") as f:
            f.write(f"{os.environ.get('PYTEST_CURRENT_TEST', '').split(' ')[0]}\t{code}\t{err.strip().splitlines()[-1:] }\n")
    return Result(code, err, out)


def debris(folder: Path) -> list[str]:
    """Scratch and replaced leftovers (``.NAME.partial-*``, ``.NAME.old-*``) in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if ".partial-" in p.name or ".old-" in p.name) \
        if folder.is_dir() else []


def check(res: Result, out: Path | None, may_pass: bool = False, warning: str | None = None) -> None:
    """The promise: exit 2 with exactly one line on stderr (``error: ...``), no traceback, no
    output ``out`` and no scratch beside it; or, where ``may_pass`` (going on is right), exit 0
    with the output written (and the ``warning`` words on a ``warning:`` line when given). A
    line that names a file under :data:`ODD` names it whole."""
    assert "Traceback" not in res.stderr, res.stderr
    if out is not None:
        assert not debris(out.parent), (debris(out.parent), res.stderr)
    if res.code == 0 and may_pass:
        assert out is None or out.exists(), res.stderr
        if warning is not None:
            assert any(ln.startswith("warning:") and warning in ln for ln in res.lines), res.stderr
        return
    assert res.code == 2, (res.code, res.stderr)
    assert len(res.lines) == 1, res.stderr
    line = res.lines[0]
    assert line.startswith("error:"), line
    if "tøy" in line or "v2" in line:
        assert ODD in line, f"a path lost text: {line}"
    assert out is None or not out.exists(), f"{out} written by a refused case"


def odd_dir(tmp_path: Path) -> Path:
    d = tmp_path / ODD
    d.mkdir()
    return d


def out_path(tmp_path: Path, name: str) -> Path:
    return tmp_path / OUT / name


def copy_tree(src: Path, dst: Path, only: tuple[str, ...] | None = None) -> Path:
    """``src`` (a folder) copied to ``dst``; with ``only``, just those entries."""
    if only is None:
        shutil.copytree(src, dst)
        return dst
    dst.mkdir(parents=True)
    for name in only:
        p = src / name
        (shutil.copytree if p.is_dir() else shutil.copy2)(p, dst / name)
    return dst


# ---------------------------------------------------------------------------------------- bases
@pytest.fixture(scope="session")
def capture_base(tiny_static_capture, tmp_path_factory) -> Path:
    """The shared static capture's parts a preprocess reads, its true intrinsics as camera.json
    (no calibration), the video also as faststart (index first, as phones write) and as frames/."""
    import av
    import cv2

    from dbb_capture.capture.footage import VideoSource

    base = tmp_path_factory.mktemp("fuzz_base") / "capture"
    base.mkdir()
    for name in ("video.mp4", "board.json", "object.json"):
        shutil.copy2(tiny_static_capture / name, base / name)
    shutil.copy2(tiny_static_capture / "ground_truth" / "camera.json", base / "camera.json")
    with av.open(str(base / "video.mp4")) as src, \
            av.open(str(base / "faststart.mp4"), "w", options={"movflags": "faststart"}) as dst:
        stream = dst.add_stream_from_template(src.streams.video[0])
        for packet in src.demux(src.streams.video[0]):
            if packet.dts is not None:
                packet.stream = stream
                dst.mux(packet)
    (base / "frames").mkdir()
    v = VideoSource(base / "video.mp4")
    for f in v.read(range(v.info.n_frames)):
        cv2.imwrite(str(base / "frames" / f"{f.name}.png"), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
    return base


def capture_copy(base: Path, tmp_path: Path, footage: str = "video") -> Path:
    """A capture under :data:`ODD` made of ``base``'s parts: footage ``video`` (as written),
    ``faststart`` (as video.mp4) or ``frames``."""
    cap = odd_dir(tmp_path) / "capture"
    copy_tree(base, cap, ("board.json", "object.json", "camera.json"))
    if footage == "frames":
        shutil.copytree(base / "frames", cap / "frames")
    else:
        shutil.copy2(base / ("faststart.mp4" if footage == "faststart" else "video.mp4"), cap / "video.mp4")
    return cap


PREPROCESS = ("--stop-after", "poses", "--workers", "1")     # the stage every capture input reaches


@pytest.fixture(scope="session")
def static_bundle_zip(static_bundle, tmp_path_factory) -> Path:
    """The shared static bundle as a ``.dbb`` zip (as ``dbb-export bundle --zip`` writes it)."""
    import zipfile

    out = tmp_path_factory.mktemp("fuzz_zip") / "static.dbb"
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(static_bundle.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(static_bundle).as_posix())
    return out


def reseal(bundle: Path) -> None:
    """Write the hashes and sizes of the files ``bundle``'s manifest lists and its checksum again
    for the files as they are now, so a corruption reaches the reader of that file instead of
    failing the hash check (a damaged list itself is kept as it is)."""
    from dbb_capture.bundle.manifest import CHECKSUM, MANIFEST, file_entries, sha256_of

    try:
        m = json.loads((bundle / MANIFEST).read_text())
    except (UnicodeDecodeError, json.JSONDecodeError):
        m = None            # damaged text: only the checksum is written again
    if isinstance(m, dict) and isinstance(m.get("files"), list):
        now = {e.path: e for e in file_entries(bundle)}
        for e in m["files"]:
            if isinstance(e, dict) and e.get("path") in now:
                e.update(sha256=now[e["path"]].sha256, bytes=now[e["path"]].bytes)
        (bundle / MANIFEST).write_text(json.dumps(m, indent=2, allow_nan=True))
    (bundle / CHECKSUM).write_text(f"{sha256_of(bundle / MANIFEST)}  {MANIFEST}\n")


def cameras_doc(bundle: Path, n: int = 2, size: int = 16) -> dict:
    """A small board-frame cameras file: ``n`` cameras on a ring around ``bundle``'s object."""
    import numpy as np

    from dbb_capture.geometry.conventions import opengl_from_opencv
    from dbb_capture.geometry.transforms import look_at

    obj = json.loads((bundle / "manifest.json").read_text())["object"]
    c, d = np.asarray(obj["center"], float), 4.0 * float(obj["radius"])
    frames = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = c + d * np.array([0.8 * np.cos(a), 0.8 * np.sin(a), -0.6])
        c2w = look_at(eye, c, np.array([0.0, 0.0, -1.0]))
        frames.append({"file_path": f"v{i}.png", "transform_matrix": opengl_from_opencv(c2w).tolist()})
    return {"camera_model": "OPENCV", "fl_x": size * 1.2, "fl_y": size * 1.2, "cx": size / 2, "cy": size / 2,
            "w": size, "h": size, "frames": frames}
