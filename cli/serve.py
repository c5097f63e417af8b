"""``dbb-serve``: stream billboards redrawn for each viewer's pose (docs/serve.md)."""

from __future__ import annotations

from pathlib import Path

import click

from .common import DbbCommand, given, refuse_with


@click.command(cls=DbbCommand, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.argument("sources", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on. Anything but loopback requires a token (printed in the URL).")
@click.option("--port", default=8765, show_default=True, type=click.IntRange(0, 65535),
              help="Port of the viewer (/) and the dbb-stream/1 websocket (/ws).")
@click.option("--seed-port", type=click.IntRange(1, 65535), default=None,
              help="Also speak the thesis's TCP protocol (its Unity client): object i on SEED_PORT + i "
                   "(the thesis's server used 6006).")
@click.option("--seed-size", default=256, show_default=True, type=int,
              help="Side in pixels of the thesis protocol's frames.")
@click.option("--max-size", default=512, show_default=True, type=int,
              help="Largest canvas side in pixels (canvases follow the billboard's size on screen).")
@click.option("--token", default=None,
              help="Token clients must present (default: none on loopback, a random one otherwise).")
@click.option("--open", "open_browser", is_flag=True, help="Open the viewer in a browser.")
@click.version_option(package_name="dbb-capture")
def main(sources, host, port, seed_port, seed_size, max_size, token, open_browser) -> None:
    """Serve billboard bundles (folders or .dbb zips) or one scene.json that places several: each
    object renders in its own process for every client's pose, streamed over dbb-stream/1
    (docs/protocol.md). Ctrl-C stops."""
    from dbb_capture.serve.run import serve_forever

    if seed_port is None:
        refuse_with(given("seed_size"), "applies with --seed-port only (the thesis protocol's frames)")
    serve_forever(list(sources), host, port, seed_port, seed_size, max_size, token, open_browser)
