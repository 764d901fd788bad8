"""The profile a command uses for a recording: the one given with --profile, else, for a
format whose recordings describe their board (SToF-Chirp's sensor_specs.yaml), the built-in
profile they name; the calibration (if any) over it."""

from __future__ import annotations

from pathlib import Path

import click

from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import apply_calibration, resolve_profile


def recording_profile(path, fmt, profile_name, calibration, *, param: str = "profile_name"):
    """--profile when the user gave it; a SToF-Chirp recording's own board otherwise."""
    from spiel_edge.runtime.recorded import format_of

    ctx = click.get_current_context(silent=True)
    given = ctx is None or ctx.get_parameter_source(param) == click.core.ParameterSource.COMMANDLINE
    if given or format_of(Path(path), fmt) != "stof-chirp":
        return resolve_profile(profile_name, calibration)
    from spiel_edge.recordings.stof_chirp import find_specs, profile_for_specs, read_specs

    specs = find_specs(path)
    if specs is None:
        raise ConfigError(f"{path}: no sensor_specs.yaml in it or above it; give --profile")
    profile = profile_for_specs(read_specs(specs), str(specs))
    return apply_calibration(profile, calibration) if calibration else profile
