"""What a node sees of the batch's folders: run on every node before any stage, so it imports
nothing but the standard library (a worker starts it in well under a second)."""

from __future__ import annotations

import socket
from pathlib import Path


def sees(marker: str, token: str, captures: str) -> tuple[str, str | None]:
    """On one node: its host name, and what it cannot see (None: the marker holds ``token`` and
    the captures folder is there)."""
    host = socket.gethostname()
    try:
        if Path(marker).read_text().strip() != token:
            return host, f"{marker} holds another batch's token"
    except OSError as e:
        return host, f"cannot read {marker} ({e.strerror})"
    if not Path(captures).is_dir():
        return host, f"cannot see the captures folder {captures}"
    return host, None
