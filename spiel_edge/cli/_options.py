"""Options shared by several commands."""

from __future__ import annotations

import click

from spiel_edge.profile.schema import Profile, apply_calibration, load_profile

profile_option = click.option(
    "--profile",
    "profile_name",
    default="spiel-icra23",
    show_default=True,
    help="Built-in device profile name or a profile .toml path.",
)
calibration_option = click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="Calibration .toml (from `spiel-edge calibrate`) applied over the profile.",
)
association_option = click.option(
    "--association",
    type=click.Choice(["auto", "onnx", "geometric"]),
    default=None,
    help="Echo association (default: the profile's; auto = onnx when the model loads).",
)


def resolve_profile(profile_name: str, calibration: str | None) -> Profile:
    profile = load_profile(profile_name)
    if calibration:
        profile = apply_calibration(profile, calibration)
    return profile
