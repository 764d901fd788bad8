"""Pictures for a person (PNG): A-scans with echoes and MEMG fits, positions and tracks,
calibration before and after, evaluation error by position (``spiel-edge view``, ``--plot``).

matplotlib is the ``plot`` extra: imported only here, only when a picture is asked for, and
checked before a command does any work (:func:`require_matplotlib`).
"""

from __future__ import annotations

from spiel_edge.errors import ConfigError

EXTRA_HINT = "pip install 'spiel-edge[plot]'"


def require_matplotlib(what: str = "--plot") -> None:
    """One ConfigError line naming the extra when matplotlib is not installed."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ConfigError(f"{what} needs matplotlib, the 'plot' extra: {EXTRA_HINT}") from None


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display needed)."""
    require_matplotlib()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
