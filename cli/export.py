"""``dbb-export``: package a trained run as a billboard bundle and render it."""

from __future__ import annotations

import click

from .common import DbbGroup


@click.group(cls=DbbGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="dbb-capture")
def main() -> None:
    """Export stage: bundles with a proxy mesh, and renders from them."""
