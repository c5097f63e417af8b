"""What every benchmark script does with its result: print it as JSON, and keep it if asked."""

from __future__ import annotations

import json
from pathlib import Path


def emit(result, path: Path | None) -> int:
    """Print ``result`` as indented JSON; also write it to ``path`` when given. Returns 0."""
    text = json.dumps(result, indent=2)
    print(text)
    if path:
        path.write_text(text + "\n")
    return 0
