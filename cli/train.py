"""``dbb-train``: fit a billboard model to a preprocessed dataset."""

from __future__ import annotations

import click

from .common import DbbGroup


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="dbb-capture")
def main() -> None:
    """Training stage: static objects (PlenOctree) and dynamic objects (RSSM)."""
