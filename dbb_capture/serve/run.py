"""Running ``dbb-serve``: what to serve from the command line's paths, start-up with progress,
the ready line, and a clean stop on Ctrl-C or SIGTERM."""

from __future__ import annotations

import asyncio
import os
import signal
import webbrowser
from pathlib import Path

from ..bundle.manifest import open_bundle
from ..core.errors import DbbError
from ..core.progress import console, progress
from .scene import Placement, is_scene_file, load_scene, row_of
from .server import Server


def placements_of(sources: list[Path]) -> list[Placement]:
    """One ``scene.json``, or bundles (folders or ``.dbb``) set side by side (:func:`~.scene.row_of`)."""
    sources = [Path(s) for s in sources]
    if not sources:
        raise DbbError("nothing to serve: give one or more bundles or a scene file")
    scenes = [s for s in sources if is_scene_file(s)]
    if scenes:
        if len(sources) > 1:
            raise DbbError("give either one scene file or bundles, not both")
        return load_scene(scenes[0])
    sizes = []
    for s in sources:
        with open_bundle(s) as b:
            sizes.append(float(b.manifest.canvas["size_m"]))
    return row_of(sources, sizes)


def node_modules() -> Path | None:
    """The npm packages the viewer loads (three.js, cannon-es): ``$DBB_NODE_MODULES``, or the
    repository's ``node_modules`` beside an editable install (``npm ci``, which scripts/setup.sh
    runs); None where neither has three.js (the page then says what is missing)."""
    env = os.environ.get("DBB_NODE_MODULES")
    for p in ([Path(env)] if env else []) + [Path(__file__).resolve().parents[2] / "node_modules"]:
        if (p / "three" / "package.json").is_file():
            return p
    return None


def viewer_roots() -> dict[str, Path]:
    """URL prefixes of the viewer's files (empty when the package ships no viewer): the page at
    ``/`` and its JavaScript packages at ``/vendor/`` (when installed)."""
    here = Path(__file__).parent / "viewer"
    if not here.is_dir():
        return {}
    roots = {"/": here}
    modules = node_modules()
    if modules is not None:
        roots["/vendor/"] = modules
    return roots


def serve_forever(sources: list[Path], host: str = "127.0.0.1", port: int = 8765, seed_port: int | None = None,
                  seed_size: int = 256, max_size: int = 512, token: str | None = None,
                  open_browser: bool = False) -> None:
    """Load every object (verifying its bundle), print the URL, serve until Ctrl-C or SIGTERM."""
    placements = placements_of(sources)
    if seed_port is not None and seed_port + len(placements) - 1 > 65535:
        raise DbbError("{=seed_port}: one port per object from SEED_PORT on must stay below 65536")
    if not 16 <= seed_size <= 2048:
        raise DbbError("{=seed_size} must be from 16 to 2048 pixels")

    async def main() -> None:
        server = Server(placements, host, port, seed_port, seed_size, max_size, token, viewer_roots())
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, server.stop)
        with progress(transient=True) as prog:
            task = prog.add_task("loading", total=len(placements), info="verifying bundles, starting renderers")
            await server.start(lambda o: prog.advance(task))
        for o in server.objects:
            console.print(f"  object {o.index} {o.placement.id}: {o.kind}, {o.placement.bundle}", markup=False)
        console.print(f"dbb-serve ready: {server.url} (stream {server.url.replace('http', 'ws', 1).split('?')[0]}ws)",
                      markup=False)
        if seed_port is not None:
            last = seed_port + len(placements) - 1
            console.print(f"thesis protocol (Unity client): tcp {host}:{seed_port}"
                          + (f"-{last}, one port per object" if last > seed_port else ""), markup=False)
        if open_browser:
            webbrowser.open(server.url)
        await server.serve()
        console.print("dbb-serve stopped", markup=False)

    asyncio.run(main())
