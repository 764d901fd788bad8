"""A fake pyusb backend: virtual boards as USB devices, so ``usb://`` runs the real pyusb
stack (device/config/interface/endpoint descriptors, string descriptors, claim, bulk
transfers, ENODEV on unplug) without hardware or libusb.

    backend = FakeUsbBackend([SimDevice(SimOptions.from_url("sim://u?scene=model"))])
    DeviceSession("usb://1209:0001", link_options={"backend": backend})
"""

from __future__ import annotations

import errno
import time
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import usb.backend
import usb.core

from spiel_edge.sim.device import DeviceGone, SimDevice

BULK = 0x02
EP_IN, EP_OUT = 0x81, 0x01
VENDOR_CLASS = 0xFF
LANG_EN_US = 0x0409
STRINGS = {1: "spiel-edge", 2: "spiel virtual board"}  # 3: the serial number
MIN_SLEEP_S = 0.0002


@dataclass(frozen=True)
class _DeviceId:
    slot: int
    device: SimDevice
    generation: int


@dataclass
class _Handle:
    dev: _DeviceId
    configuration: int = 0


def _gone() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)


class FakeUsbBackend(usb.backend.IBackend):
    """Each SimDevice is one device with a vendor interface and bulk endpoints 0x81/0x01."""

    def __init__(self, devices: list[SimDevice], *, max_packet: int = 512):
        super().__init__()
        self.devices = list(devices)
        self.max_packet = max_packet

    # --- enumeration and descriptors -----------------------------------------------------

    def enumerate_devices(self):
        for slot, device in enumerate(self.devices):
            device.update(device.clock())
            if device.plugged:
                yield _DeviceId(slot, device, device.generation)

    def get_parent(self, dev: _DeviceId) -> None:
        return None

    def get_device_descriptor(self, dev: _DeviceId) -> Any:
        opts = dev.device.options
        return SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=opts.vid,
            idProduct=opts.pid,
            bcdDevice=0x0100,
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3,
            bNumConfigurations=1,
            address=dev.slot + 10 * dev.generation % 100 + 1,
            bus=1,
            port_number=dev.slot + 1,
            port_numbers=(dev.slot + 1,),
            speed=3,
        )

    def get_configuration_descriptor(self, dev: _DeviceId, config: int) -> Any:
        if config != 0:
            raise IndexError("one configuration only")
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=32,
            bNumInterfaces=1,
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0x80,
            bMaxPower=50,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev: _DeviceId, intf: int, alt: int, config: int) -> Any:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError("one interface, one alternate setting")
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=0,
            bAlternateSetting=0,
            bNumEndpoints=2,
            bInterfaceClass=VENDOR_CLASS,
            bInterfaceSubClass=0,
            bInterfaceProtocol=0,
            iInterface=0,
            extra_descriptors=[],
        )

    def get_endpoint_descriptor(
        self, dev: _DeviceId, ep: int, intf: int, alt: int, config: int
    ) -> Any:
        if ep not in (0, 1) or (intf, alt, config) != (0, 0, 0):
            raise IndexError("two endpoints")
        return SimpleNamespace(
            bLength=7,
            bDescriptorType=5,
            bEndpointAddress=(EP_IN, EP_OUT)[ep],
            bmAttributes=BULK,
            wMaxPacketSize=self.max_packet,
            bInterval=0,
            bRefresh=0,
            bSynchAddress=0,
            extra_descriptors=[],
        )

    # --- handles -------------------------------------------------------------------------

    def _alive(self, handle: _Handle) -> SimDevice:
        device = handle.dev.device
        device.update(device.clock())
        if not device.plugged or device.generation != handle.dev.generation:
            raise _gone()
        return device

    def open_device(self, dev: _DeviceId) -> _Handle:
        handle = _Handle(dev)
        self._alive(handle)
        return handle

    def close_device(self, dev_handle: _Handle) -> None:
        pass

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        self._alive(dev_handle)
        dev_handle.configuration = config_value

    def get_configuration(self, dev_handle: _Handle) -> int:
        self._alive(dev_handle)
        return dev_handle.configuration

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        self._alive(dev_handle)

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        pass

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        return False

    # --- transfers -----------------------------------------------------------------------

    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: Any, timeout: int) -> int:
        device = self._alive(dev_handle)
        try:
            device.write(bytes(data), dev_handle.dev.generation)
        except DeviceGone:
            raise _gone() from None
        return len(data)

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        device = self._alive(dev_handle)
        deadline = time.monotonic() + timeout / 1000.0
        while True:
            try:
                data = device.read(len(buff), dev_handle.dev.generation)
            except DeviceGone:
                raise _gone() from None
            if data:
                buff[: len(data)] = type(buff)(buff.typecode, data)
                return len(data)
            now = time.monotonic()
            if now >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            device.wait(now, deadline, MIN_SLEEP_S)

    def ctrl_transfer(
        self,
        dev_handle: _Handle,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        """GET_DESCRIPTOR(STRING) only: language ids and the three strings."""
        device = self._alive(dev_handle)
        if bRequest != 0x06 or wValue >> 8 != 0x03:
            raise usb.core.USBError("Pipe error (request not supported)", -9, errno.EPIPE)
        index = wValue & 0xFF
        if index == 0:
            body = LANG_EN_US.to_bytes(2, "little")
        else:
            text = device.options.serial if index == 3 else STRINGS.get(index)
            if text is None:
                raise usb.core.USBError("Pipe error (no such string)", -9, errno.EPIPE)
            body = text.encode("utf-16-le")
        desc = (bytes([2 + len(body), 0x03]) + body)[: len(data)]
        data[: len(desc)] = type(data)(data.typecode, desc)
        return len(desc)
