"""spiel-edge: 3-D ultrasonic echolocation (PaCE) for robots.

Data flow, mirrored by the package layout:
bytes (link/) -> frames (firmware_protocol) -> acquisitions (device/, io/) ->
echoes (pipeline/preprocess, detect, memg) -> features (pipeline/features) ->
associations (pipeline/associate, scene) -> positions (pipeline/echo_timing, locate) ->
tracks (track/) -> outputs (outputs/); runtime/ runs it, cli/ is the command line.
"""

from spiel_edge import _shipped
from spiel_edge.errors import SpielError

_shipped.select_cpu()  # before anything imports numba: a wheel's prebuilt kernels need it

__version__ = "0.1.0"
__all__ = ["SpielError", "__version__"]
