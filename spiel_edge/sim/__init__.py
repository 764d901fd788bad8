"""The virtual board: the device side of spiel_edge.protocol, with scenes and fault injection.

Reach it as ``sim://[NAME][?query]`` (see :mod:`spiel_edge.link.sim_options` for the keys), on a
pseudo-terminal (``spiel-edge simulate --pty``), or through the fake pyusb backend
(:mod:`spiel_edge.sim.usb_backend`) as ``usb://VID:PID``.
Tests that play a robot move the model scene's target with
:func:`spiel_edge.sim.protocol_sim.place_target` (guided calibration).
"""

from spiel_edge.link.sim_options import SimOptions
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.device import SimDevice
from spiel_edge.sim.flash import Flash, PowerCut
from spiel_edge.sim.scenes import EchoModelScene, ReplayScene, SceneFrame

__all__ = [
    "EchoModelScene",
    "Flash",
    "PowerCut",
    "ReplayScene",
    "SceneFrame",
    "SimDevice",
    "SimOptions",
    "VirtualBoard",
]
