"""spiel-edge: 3-D ultrasonic echolocation (PaCE) for robots.

Data flow, mirrored by the package layout:
bytes (link/) -> frames (spiel_edge.protocol) -> acquisitions (device/, safety/) ->
echoes (pipeline/preprocess, detect, memg) -> features (pipeline/features) ->
associations (pipeline/associate, scene) -> positions (pipeline/echo_timing, locate) ->
tracks (track/) -> outputs (outputs/); runtime/ runs it, cli/ is the command line.
"""

import os as _os
import sys as _sys

if _os.path.basename(_sys.argv[0] if _sys.argv else "") == "spiel-edge" or list(
    getattr(_sys, "orig_argv", [])[1:3]
) == ["-m", "spiel_edge.cli"]:
    from spiel_edge import _early  # noqa: F401  # the command itself: signals recorded from here

from spiel_edge.errors import SpielError  # noqa: E402

__version__ = "0.1.0"
__all__ = ["SpielError", "__version__"]
