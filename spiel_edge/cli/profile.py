"""``spiel-edge profile``: list the built-in device profiles, print one to copy and edit."""

from __future__ import annotations

from importlib import resources

import click

from spiel_edge.profile.schema import builtin_profiles, load_profile


@click.group("profile")
def command() -> None:
    """Device profiles: geometry, timing and pipeline tuning as TOML."""


@command.command("list")
def list_profiles() -> int:
    """Names of the built-in profiles."""
    for name in builtin_profiles():
        click.echo(f"{name}\t{load_profile(name).description}")
    return 0


@command.command("show")
@click.argument("name", default="spiel-icra23")
def show(name: str) -> int:
    """Print a built-in profile (with its comments): `spiel-edge profile show > my-board.toml`."""
    load_profile(name)  # validates the name; raises ConfigError listing the known ones
    click.echo(
        (resources.files("spiel_edge") / "profile" / "builtin" / f"{name}.toml").read_text(),
        nl=False,
    )
    return 0
