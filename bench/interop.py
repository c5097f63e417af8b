"""Interop with nerfstudio 1.1.5: does nerfstudio read our transforms.json, crops.json and COLMAP model right?

Runs nerfstudio's own loaders in a venv of their own and compares what they produce with what
this library computes (issue 39). The bars:

1. rays: for pixels of every crop (``crops.json``), every full frame (``transforms.json``) and
   every lego frame (the NeRF-synthetic scene, read by nerfstudio's Blender parser and, round
   trip, from a ``transforms.json`` that our writer made of it), the ray that
   ``Cameras.generate_rays`` makes from the dataparser's outputs (pixel (u, v) in OpenCV's
   convention = nerfstudio coords (v + 0.5, u + 0.5)) equals the ray of our
   ``dbb_capture.geometry.rays.pixel_rays`` on the frames of ``dbb_capture.datasets.transforms.load_dataset``:
   origin and direction within 1e-6. ``NerfstudioDataParser`` runs with orientation_method="none",
   center_method="none", auto_scale_poses=False; the runs with default options (theirs and
   ``ColmapDataParser``'s) are compared after undoing the dataparser transform and scale.
2. identity: with those none-options the dataparser transform of our transforms.json (and
   crops.json) is the identity and its scale 1 (the file's ``applied_transform``; without it
   nerfstudio inserts [[0,1,0],[1,0,0],[0,0,-1]] when colmap/sparse/0 exists). The default
   options' transform and scale are reported (orientation "up", centre "poses", auto scale).
3. points: with load_3D_points=True the outputs' ``points3D_xyz`` (splatfacto's initial point
   cloud, from ``ply_file_path`` = sparse_pc.ply) is non-empty.
4. colmap: ``ColmapDataParser`` with default options loads the dataset folder (images/,
   colmap/sparse/0), all frames, and its poses, mapped back through its transform and scale,
   agree with transforms.json: rotation within 1e-4 degrees, position within 1e-5 m (nerfstudio
   keeps poses in float32).

Run (from the repository root, with the project venv):

    .venv/bin/python bench/interop.py                      # venv, dataset, checks under out/interop
    .venv/bin/python bench/interop.py --dataset DS         # a dataset made by `dbb-capture preprocess`

The first run makes the nerfstudio venv (out/interop/venv, with the Python running this script,
which must be 3.11 for the torch wheels; 8.3 GB, about 6 minutes: pip takes torch and torchvision
from the machine's local wheels, the rest from the package index) and, without --dataset,
preprocesses sample_data/static into out/interop/dataset (about 3 minutes); later runs reuse
both. The checks themselves take under a minute. Prints a table, writes out/interop/results.json, exits 1 if a bar fails.

Pins: ``pip install torch==2.14.1 torchvision==0.29.1`` first, then ``nerfstudio==1.1.5`` with a
constraints file holding the same two pins. torchvision must match torch exactly: a torchvision
built for another torch makes pip replace torch, with an unpinned (CUDA, several GB) build from
the index. nerfstudio 1.1.5 then installs as is, with no further pins (it brings numpy 1.26.4,
gsplat 1.4.0, open3d 0.20.0; fpsample and pyliblzfse build from source). The nerfstudio side of
the checks is this file run by that venv's Python with --nerfstudio-side: it imports nerfstudio
only (never dbb_capture); the two sides exchange JSON and npz files. stdin is /dev/null, so
nerfstudio's prompts cannot block (none is reached with these datasets and options).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PINS = ("torch==2.14.1", "torchvision==0.29.1")
NERFSTUDIO = "nerfstudio==1.1.5"
RAY_TOL = 1e-6
POSE_TOL_DEG, POSE_TOL_M = 1e-4, 1e-5
NONE = {"orientation_method": "none", "center_method": "none", "auto_scale_poses": False, "eval_mode": "all"}
ALL_SPLITS = ["train", "val"]


# ---------------------------------------------------------------- nerfstudio side (its venv)

def nerfstudio_side(request: Path) -> None:
    """Run each case's dataparser, generate the requested rays, dump outputs next to ``request``."""
    import torch
    from nerfstudio.data.dataparsers import (
        blender_dataparser,
        colmap_dataparser,
        nerfstudio_dataparser,
    )

    configs = {"nerfstudio": nerfstudio_dataparser.NerfstudioDataParserConfig,
               "blender": blender_dataparser.BlenderDataParserConfig, "colmap": colmap_dataparser.ColmapDataParserConfig}
    work = request.parent
    summary = {}
    for case in json.loads(request.read_text())["cases"]:
        parser = configs[case["parser"]](data=Path(case["data"]), **case["options"]).setup()
        q = np.load(work / f"{case['key']}_query.npz")
        o, d = np.zeros((len(q["cam"]), 3)), np.zeros((len(q["cam"]), 3))
        found = np.zeros(len(q["cam"]), bool)
        images, c2w, points = [], [], None
        for split in case["splits"]:
            out = parser.get_dataparser_outputs(split)
            index = {os.path.realpath(p): i for i, p in enumerate(out.image_filenames)}
            for k, img in enumerate(q["images"]):
                i, sel = index.get(os.path.realpath(str(img))), q["cam"] == k
                if i is None or not sel.any():
                    continue
                coords = torch.from_numpy(q["pix"][sel][:, ::-1] + 0.5).float()
                rays = out.cameras.generate_rays(torch.full((len(coords), 1), i, dtype=torch.long), coords)
                o[sel], d[sel], found[sel] = rays.origins.double().numpy(), rays.directions.double().numpy(), True
            images += [str(p) for p in out.image_filenames]
            c2w.append(out.cameras.camera_to_worlds.double().numpy())
            if "points3D_xyz" in out.metadata:
                points = len(out.metadata["points3D_xyz"])
        summary[case["name"]] = {"transform": out.dataparser_transform.double().tolist(),
                                 "scale": float(out.dataparser_scale), "images": images, "points": points}
        np.savez(work / f"{case['key']}_nerfstudio.npz", o=o, d=d, found=found, c2w=np.concatenate(c2w))
    (work / "nerfstudio.json").write_text(json.dumps(summary))


# ---------------------------------------------------------------- project side

def ensure_venv(venv: Path, log: Path) -> dict:
    """The nerfstudio venv: made and installed once (its install record kept inside), then reused."""
    py, record = venv / "bin" / "python", venv / "interop-install.json"
    if record.is_file() and py.is_file():
        return {**json.loads(record.read_text()), "reused": True}
    t0 = time.time()
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    (venv / "constraints.txt").write_text("\n".join(PINS) + "\n")
    with log.open("w") as f:
        for args in ([*PINS], ["-c", str(venv / "constraints.txt"), NERFSTUDIO]):
            print(f"pip install {' '.join(args)}  (log: {log})", flush=True)
            subprocess.run([str(py), "-m", "pip", "install", *args], check=True, stdout=f,
                           stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    names = ("torch", "torchvision", "nerfstudio", "numpy")
    code = f"import importlib.metadata as m; print(*(m.version(p) for p in {names}))"
    versions = subprocess.run([str(py), "-c", code], check=True, capture_output=True, text=True).stdout.split()
    size = subprocess.run(["du", "-sb", str(venv)], check=True, capture_output=True, text=True).stdout.split()[0]
    rec = {"install_seconds": round(time.time() - t0), "size_gb": round(int(size) / 1e9, 2),
           "versions": dict(zip(names, versions))}
    record.write_text(json.dumps(rec, indent=2) + "\n")
    return {**rec, "reused": False}


def ensure_dataset(path: Path | None, work: Path) -> Path:
    """``path``, or a dataset of sample_data/static preprocessed once into ``work``/dataset."""
    if path is not None:
        return path.resolve()
    ds = work / "dataset"
    if not (ds / "crops.json").is_file():
        print(f"preprocess sample_data/static -> {ds}", flush=True)
        # The background field only colours the crops: few steps do for these checks.
        subprocess.run([str(Path(sys.executable).parent / "dbb-capture"), "preprocess",
                        str(REPO / "sample_data/static"), "-o", str(ds), "--background-steps", "20",
                        "--overwrite"], check=True, stdin=subprocess.DEVNULL)
    return ds.resolve()


def query(frames, per_camera: int, rng) -> tuple[dict, np.ndarray, np.ndarray]:
    """Pixels to check (all of a small image, else its corners, centre and ``per_camera`` random
    ones) and our rays through them: the query for nerfstudio, origins, directions."""
    from dbb_capture.geometry.rays import pixel_rays

    cams, pixs, os_, ds = [], [], [], []
    for k, f in enumerate(frames):
        w, h = f.intr.width, f.intr.height
        if w * h <= 128 * 128:
            pix = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)
        else:
            pix = np.concatenate([[[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [w // 2, h // 2]],
                                  np.stack([rng.integers(0, w, per_camera), rng.integers(0, h, per_camera)], 1)])
        o, d = pixel_rays(f.intr, f.c2w, np.float64)
        cams.append(np.full(len(pix), k))
        pixs.append(pix)
        os_.append(o[pix[:, 1], pix[:, 0]])
        ds.append(d[pix[:, 1], pix[:, 0]])
    q = {"images": np.array([str(f.image_path) for f in frames]), "cam": np.concatenate(cams),
         "pix": np.concatenate(pixs)}
    return q, np.concatenate(os_), np.concatenate(ds)


def to_world(T: np.ndarray, s: float, x: np.ndarray, point: bool) -> np.ndarray:
    """Undo a dataparser transform ``T`` (3, 4) and scale ``s`` on points or directions (..., 3)."""
    R, t = T[:, :3], T[:, 3]
    return (x / s - t) @ R if point else x @ R


def rot_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between rotations (..., 3, 3), exact for small angles."""
    return np.degrees(2 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=(-2, -1)) / (2 * np.sqrt(2)), 0, 1)))


def transform_report(T: np.ndarray, s: float, c2w: np.ndarray) -> dict:
    """A dataparser transform in words: its rotation, translation, scale and where cameras end up."""
    return {"transform": np.round(T, 6).tolist(), "scale": s,
            "rotation_deg": float(rot_deg(T[:, :3], np.eye(3))), "translation": np.round(T[:, 3], 6).tolist(),
            "mean_camera_position_out": np.round(c2w[:, :, 3].mean(0), 6).tolist(),
            "max_abs_camera_coordinate_out": round(float(np.abs(c2w[:, :, 3]).max()), 6)}


def run_nerfstudio(py: Path, ex: Path, cases: list, frames: dict, per_camera: int, seed: int, log: Path):
    """Our rays for each case's pixels, then the nerfstudio side on them: (ours, its summary, its arrays)."""
    rng, ours, req = np.random.default_rng(seed), {}, []
    for i, (name, parser, data, opts, splits, fr) in enumerate(cases):
        q, o, d = query(frames[fr], per_camera, rng)
        np.savez(ex / f"case{i}_query.npz", **q)
        ours[name] = (o, d)
        req.append({"name": name, "key": f"case{i}", "parser": parser, "data": str(data), "options": opts,
                    "splits": splits})
    (ex / "request.json").write_text(json.dumps({"cases": req}))
    with log.open("w") as f:
        r = subprocess.run([str(py), __file__, "--nerfstudio-side", str(ex / "request.json")], check=False,
                           stdin=subprocess.DEVNULL, stdout=f, stderr=subprocess.STDOUT)
    if r.returncode:
        print(log.read_text()[-3000:])
        sys.exit(f"the nerfstudio side failed (exit {r.returncode}); log: {log}")
    summary = json.loads((ex / "nerfstudio.json").read_text())
    return ours, summary, {c["name"]: dict(np.load(ex / f"{c['key']}_nerfstudio.npz")) for c in req}


def check(cases: list, ours: dict, ns: dict, arrays: dict, poses: dict) -> tuple[list, dict]:
    """The four bars: table rows (bar, case, figure, limit, pass or None) and the results."""
    rows, res = [], {}
    for name, *_ in cases:   # 1: rays, mapped back through the dataparser transform and scale
        z, T, s, (o, d) = arrays[name], np.array(ns[name]["transform"]), ns[name]["scale"], ours[name]
        do = float(np.linalg.norm(to_world(T, s, z["o"], True) - o, axis=1).max())
        dd = float(np.linalg.norm(to_world(T, s, z["d"], False) - d, axis=1).max())
        ok = bool(z["found"].all()) and do <= RAY_TOL and dd <= RAY_TOL
        res[f"rays: {name}"] = {"rays": len(o), "all_found": bool(z["found"].all()), "max_origin_diff": do,
                                "max_direction_diff": dd, "pass": ok}
        rows.append(("1 rays", name, f"{len(o)} rays: |do| {do:.1e}, |dd| {dd:.1e}", f"<= {RAY_TOL:g}", ok))
    for name in ("transforms.json", "crops.json", "lego, our transforms.json"):   # 2: identity
        T, s = np.array(ns[name]["transform"]), ns[name]["scale"]
        err = float(np.abs(T - np.eye(4)[:3]).max())
        ok = err == 0 and s == 1
        res[f"identity: {name}"] = {**transform_report(T, s, arrays[name]["c2w"]), "max_abs_diff_from_identity": err,
                                    "pass": ok}
        rows.append(("2 identity", f"{name}, none-options", f"max |T - I| {err:g}, scale {s:g}", "0, 1", ok))
    defaults = "orientation_method=up, center_method=poses, auto_scale_poses=True"
    for name, key, opts in (("transforms.json, default options", "defaults: transforms.json", defaults),
                            ("colmap/sparse/0, default options", "defaults: colmap",
                             defaults + ", assume_colmap_world_coordinate_convention=True")):
        rep = transform_report(np.array(ns[name]["transform"]), ns[name]["scale"], arrays[name]["c2w"])
        res[key] = {"options": opts, **rep}
        fig = f"rotation {rep['rotation_deg']:.2f} deg, translation {rep['translation']}, scale {rep['scale']:.4f}"
        rows.append(("2 (report)", name, fig, "-", None))
    n = ns["transforms.json"]["points"]   # 3: splatfacto's points
    res["points: transforms.json"] = {"points3D_xyz": n, "pass": bool(n)}
    rows.append(("3 points", "transforms.json, load_3D_points", f"points3D_xyz: {n}", "> 0", bool(n)))
    name = "colmap/sparse/0, default options"   # 4: COLMAP poses against transforms.json
    T, s, c2w, images = np.array(ns[name]["transform"]), ns[name]["scale"], arrays[name]["c2w"], ns[name]["images"]
    mine = [poses.get(os.path.realpath(p)) for p in images]
    keep = np.array([m is not None for m in mine])
    ref = np.stack([m for m in mine if m is not None])
    ang = float(rot_deg(T[:, :3].T @ c2w[keep, :, :3], ref[:, :3, :3]).max())
    pos = float(np.linalg.norm(to_world(T, s, c2w[keep, :, 3], True) - ref[:, :3, 3], axis=1).max())
    ok = keep.all() and len(images) == len(poses) and ang <= POSE_TOL_DEG and pos <= POSE_TOL_M
    res["colmap: poses"] = {"frames": len(images), "transforms_json_frames": len(poses),
                            "points3D": ns[name]["points"], "max_rotation_diff_deg": ang, "max_position_diff_m": pos,
                            "pass": bool(ok)}
    rows.append(("4 colmap", f"{len(images)}/{len(poses)} frames, {ns[name]['points']} points",
                 f"max {ang:.1e} deg, {pos:.1e} m", f"<= {POSE_TOL_DEG:g} deg, {POSE_TOL_M:g} m", bool(ok)))
    return rows, res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=REPO / "out/interop",
                    help="folder for the venv, the dataset and the exchange files (default: out/interop)")
    ap.add_argument("--venv", type=Path, help="nerfstudio venv, made if missing (default: WORK/venv)")
    ap.add_argument("--dataset", type=Path, help="dataset made by dbb-capture preprocess (default: made "
                    "from sample_data/static into WORK/dataset)")
    ap.add_argument("--lego", type=Path, default=REPO / "../shared/data/nerf_lego",
                    help="NeRF-synthetic lego folder (default: ../shared/data/nerf_lego)")
    ap.add_argument("--pixels", type=int, default=64, help="random pixels per full-size camera (default: 64)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="results JSON (default: WORK/results.json)")
    ap.add_argument("--nerfstudio-side", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.nerfstudio_side:
        nerfstudio_side(a.nerfstudio_side)
        return 0

    from dbb_capture.datasets.transforms import load_dataset, write_transforms
    from dbb_capture.geometry.conventions import opengl_from_opencv

    work = a.work.resolve()
    ex, venv, lego_dir = work / "exchange", (a.venv or work / "venv").resolve(), a.lego.resolve()
    ex.mkdir(parents=True, exist_ok=True)
    install = ensure_venv(venv, work / "install.log")
    ds = ensure_dataset(a.dataset, work)
    lego = load_dataset(lego_dir)
    write_transforms(ex / "lego_transforms.json", lego.frames)   # the round trip through our writer
    frames = {"crop": load_dataset(ds / "crops.json").frames, "frame": load_dataset(ds / "transforms.json").frames,
              "lego": lego.frames}
    cases = [  # name, parser, data, options, splits, frames
        ("crops.json", "nerfstudio", ds / "crops.json", NONE, ["train"], "crop"),
        ("transforms.json", "nerfstudio", ds, {**NONE, "load_3D_points": True}, ["train"], "frame"),
        ("transforms.json, default options", "nerfstudio", ds, {}, ALL_SPLITS, "frame"),
        ("lego, Blender parser", "blender", lego_dir, {}, ["train"], "lego"),
        ("lego, our transforms.json", "nerfstudio", ex / "lego_transforms.json", NONE, ["train"], "lego"),
        ("colmap/sparse/0, default options", "colmap", ds, {}, ALL_SPLITS, "frame"),
    ]
    t0 = time.time()
    ours, ns, arrays = run_nerfstudio(venv / "bin/python", ex, cases, frames, a.pixels, a.seed,
                                      work / "nerfstudio.log")
    poses = {os.path.realpath(f.image_path): opengl_from_opencv(f.c2w) for f in frames["frame"]}
    rows, res = check(cases, ours, ns, arrays, poses)
    res = {"install": install, "dataset": str(ds), "nerfstudio_seconds": round(time.time() - t0, 1), **res,
           "pass": all(r[4] for r in rows if r[4] is not None)}
    width = [max(len(str(r[i])) for r in rows) for i in range(4)]
    for r in rows:
        print("  ".join(str(v).ljust(w) for v, w in zip(r, width)) + "  " + {None: "-", True: "pass"}.get(r[4], "FAIL"))
    out = a.out or work / "results.json"
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"nerfstudio venv: {install}\nresults: {out}; {'all bars pass' if res['pass'] else 'a bar FAILS'}")
    return 0 if res["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
