"""Exceptions shared by every driver. Device-specific ones subclass these in their own modules.

Every exception says which device (port) and what happened, so a one-line report is enough to act
on. They derive from `RuntimeError`, not `ValueError`: a bench failure is not bad user input.
"""

from __future__ import annotations


class DeviceError(RuntimeError):
    """Something went wrong talking to, or inside, a device."""


class TransportError(DeviceError):
    """The byte link to a device failed."""


class PortNotFound(TransportError):
    """No port matches the configured path or USB serial number."""


class PortBusy(TransportError):
    """Another process holds the port (ports are opened exclusively)."""


class PortVanished(TransportError):
    """The port disappeared while open (cable pulled, USB reset, device powered off)."""


class ReplyTimeout(TransportError):
    """No (complete) reply within the timeout."""


class ProtocolError(DeviceError):
    """Bytes arrived that do not follow the device's protocol."""


class WrongDevice(DeviceError):
    """Identification says this is not the device the settings describe; nothing was written."""


class LinkDown(DeviceError):
    """The driver is not connected (never opened, closed, or the port vanished): reconnect."""
