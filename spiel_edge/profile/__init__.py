"""Device profiles: geometry, timing and pipeline tuning as one validated frozen dataclass tree
(``schema``), read from TOML; the built-in profiles are in ``builtin/``."""

from spiel_edge.profile.schema import (
    Geometry,
    Profile,
    apply_calibration,
    builtin_profiles,
    load_profile,
)

__all__ = ["Geometry", "Profile", "apply_calibration", "builtin_profiles", "load_profile"]
