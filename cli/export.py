"""``dbb-export``: package a trained run as a billboard bundle and render it."""

from __future__ import annotations

from pathlib import Path

import click
from rich.markup import escape

from .common import DbbGroup, overwrite_option


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="dbb-capture")
def main() -> None:
    """Export stage: bundles with a proxy mesh, and renders from them."""


@main.command("bundle")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Bundle to write: a folder, or a .dbb zip with --zip.")
@click.option("--zip", "zip_it", is_flag=True, help="Write the bundle as one zip file (.dbb).")
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="The run's dataset, if it moved since training (default: the path in run.json).")
@overwrite_option
def bundle(run, out, zip_it, dataset, overwrite) -> None:
    """Package the finished training RUN (dbb-train plenoctree or rssm) as a billboard bundle:
    manifest, model, proxy mesh (.glb, bundle space) and previews."""
    from dbb_capture.bundle.build import make_bundle
    from dbb_capture.core.progress import console

    m = make_bundle(run, out, zip_it, dataset, overwrite)
    pm = m.proxy_mesh
    console.print(f"wrote {escape(str(out))}: {m.kind} bundle, {len(m.files)} files; proxy mesh: {pm['method']}, "
                  f"{pm['triangles']} triangles, watertight {pm['watertight']}", soft_wrap=True)


@main.command("render")
@click.argument("bundle", type=click.Path(path_type=Path))
@click.option("--cameras", required=True, type=click.Path(path_type=Path),
              help="transforms-style json: frames[].file_path and OpenGL camera-to-world transform_matrix, "
                   "intrinsics at the top level or per frame.")
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Folder to write, one straight RGBA PNG per frame named after its file_path.")
@click.option("--first-frame", type=click.Path(path_type=Path), default=None,
              help="Dynamic bundles: the RGBA image to start from, seen from the first camera "
                   "(default: the bundle's stored first frame).")
@click.option("--space", type=click.Choice(["board", "bundle"]), default="board", show_default=True,
              help="Frame of the cameras: the capture's board frame, or bundle space (manifest bundle_from_board).")
@overwrite_option
def render(bundle, cameras, out, first_frame, space, overwrite) -> None:
    """Render the BUNDLE (folder or .dbb) from every camera of a cameras file."""
    from dbb_capture.bundle.render import render_bundle
    from dbb_capture.core.progress import console

    paths = render_bundle(bundle, cameras, out, first_frame, space, overwrite)
    console.print(f"wrote {len(paths)} RGBA PNGs to {out}", soft_wrap=True, markup=False)


@main.command("verify")
@click.argument("bundle", type=click.Path(path_type=Path))
def verify(bundle) -> None:
    """Check BUNDLE: manifest checksum and schema, file hashes, model and proxy mesh load, and a
    fresh render matches the stored preview. Exit 2 with the first failure."""
    from dbb_capture.bundle.verify import verify_bundle
    from dbb_capture.core.progress import console

    for line in verify_bundle(bundle):
        console.print(f"[green]ok[/green] {escape(line)}", soft_wrap=True)
    console.print(f"{bundle}: verified", soft_wrap=True, markup=False)
