"""Links by URL, board discovery and the usb:// link over the fake pyusb backend."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceDisconnectedError, DeviceError
from spiel_edge.link import LinkIdentity, discover, open_link, scheme_of
from spiel_edge.link.usb_link import parse_usb_url
from spiel_edge.sim import SimDevice, SimOptions
from spiel_edge.sim.usb_backend import FakeUsbBackend


def sim_device(query: str = "") -> SimDevice:
    return SimDevice(SimOptions.from_url(f"sim://usb?{query}"))


def test_schemes_and_usb_urls():
    assert scheme_of("/dev/ttyACM0") == "serial" and scheme_of("SIM://x") == "sim"
    assert parse_usb_url("usb://1209:0001") == (0x1209, 1, None)
    assert parse_usb_url("usb://1209:ABCD/SN-7") == (0x1209, 0xABCD, "SN-7")
    with pytest.raises(DeviceError, match="expected usb://VID:PID"):
        parse_usb_url("usb://12345:1")


def test_sim_options_are_validated():
    opts = SimOptions.from_url("sim://b2?ber=1e-4&unplug_after=3&shuffle=1&targets=0,0,150")
    assert (opts.name, opts.ber, opts.unplug_after, opts.shuffle) == ("b2", 1e-4, 3, True)
    for bad in ("sim://?ber=2", "sim://?unplug_after=x", "sim://?scene=lab", "sim://?nope=1"):
        with pytest.raises(ValueError):
            SimOptions.from_url(bad)


def test_usb_link_streams_through_pyusb_and_survives_unplugs():
    device = sim_device("scene=model&unplug_after=40&unplug_ms=50&unplug_count=2&serial=USB7")
    backend = FakeUsbBackend([device])
    with DeviceSession("usb://1209:0001/USB7", link_options={"backend": backend}) as session:
        assert session.identity == LinkIdentity("usb://1209:0001/USB7", 0x1209, 1, "USB7")
        session.start_stream(rate_hz=500)
        stop = threading.Event()
        timer = threading.Timer(20.0, stop.set)
        timer.start()
        n = 0
        for _ in session.acquisitions(stop):
            n += 1
            if n >= 120:
                break
        timer.cancel()
        assert n == 120 and session.counters.reconnects == 2 and device.unplugs == 2


def test_usb_link_errors():
    backend = FakeUsbBackend([sim_device("serial=ONE")])
    with pytest.raises(DeviceDisconnectedError, match="no such USB device"):
        open_link("usb://1209:0001/TWO", backend=backend)
    link = open_link("usb://1209:0001/ONE", backend=backend)
    assert link.read(0.01) == b""  # nothing asked, nothing sent: a timeout, not an error
    backend.devices[0].unplug(backend.devices[0].clock(), 10.0)
    with pytest.raises(DeviceDisconnectedError):
        link.read(0.01)


def test_default_port_finds_one_board_or_says_how_to_name_one(monkeypatch):
    monkeypatch.setattr(discover.serial.tools.list_ports, "comports", lambda: [])
    empty = FakeUsbBackend([])
    with pytest.raises(DeviceError, match="--port sim://"):
        discover.default_port(usb_backend=empty)
    one = FakeUsbBackend([sim_device("serial=A1")])
    assert discover.default_port(usb_backend=one) == "usb://1209:0001/A1"
    two = FakeUsbBackend([sim_device("serial=A1"), sim_device("serial=B2")])
    with pytest.raises(DeviceError, match="several boards"):
        discover.default_port(usb_backend=two)


def test_serial_ports_are_found_again_by_vid_pid_serial(monkeypatch):
    port = SimpleNamespace(device="/dev/ttyACM3", vid=0x1209, pid=1, serial_number="S9")
    other = SimpleNamespace(device="/dev/ttyUSB0", vid=0x0403, pid=0x6001, serial_number="FT")
    monkeypatch.setattr(discover.serial.tools.list_ports, "comports", lambda: [other, port])
    assert [b.url for b in discover.find_serial_boards()] == ["/dev/ttyACM3"]
    assert discover.find_again(LinkIdentity("/dev/ttyACM0", 0x1209, 1, "S9")) == "/dev/ttyACM3"
    assert discover.find_again(LinkIdentity("/dev/ttyACM0", 0x1209, 1, "S8")) is None
    assert discover.find_again(LinkIdentity("/dev/pts/4")) is None
