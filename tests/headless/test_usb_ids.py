"""One place for the board's USB ids: discovery, udev rule, doctor and the virtual board."""

from __future__ import annotations

import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.link import discover, usb_ids
from spiel_edge.link.sim_options import SimOptions
from spiel_edge.service import kit


def test_every_consumer_reads_the_same_ids():
    assert discover.BOARD_USB_IDS == usb_ids.BOARD_USB_IDS == kit.usb_ids()
    assert (SimOptions().vid, SimOptions().pid) == usb_ids.BOARD_USB_IDS[0]
    vid, pid = usb_ids.BOARD_USB_IDS[0]
    assert f'ATTRS{{idVendor}}=="{vid:04x}", ATTRS{{idProduct}}=="{pid:04x}"' in kit.render_udev()


def test_environment_overrides_the_ids(monkeypatch):
    monkeypatch.setenv(usb_ids.ENV_VAR, "cafe:0042, 1209:ABCD")
    assert usb_ids.board_usb_ids() == ((0xCAFE, 0x0042), (0x1209, 0xABCD))
    rule = kit.render_udev()
    assert 'ATTRS{idVendor}=="cafe", ATTRS{idProduct}=="0042"' in rule
    assert "1209:0001" not in rule
    assert usb_ids.board_usb_ids({}) == usb_ids.BOARD_USB_IDS


@pytest.mark.parametrize("bad", ["cafe", "cafe:", "xyz:1", "10000:1", ",", "1:2:3"])
def test_bad_ids_are_a_clear_config_error(bad):
    with pytest.raises(ConfigError, match="SPIEL_USB_IDS"):
        usb_ids.parse_usb_ids(bad)
