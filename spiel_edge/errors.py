"""The exception root of spiel-edge; every error the package raises derives from SpielError."""


class SpielError(Exception):
    """Root of all spiel-edge errors."""


class ConfigError(SpielError, ValueError):
    """A profile, calibration or config file is invalid (the message names the key)."""


class InputError(SpielError, ValueError):
    """An acquisition or recording is malformed (the message names the file)."""


class ModelError(SpielError):
    """The association model is missing or unusable."""


class DeviceError(SpielError, OSError):
    """The board is missing, unplugged or misbehaving."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The board did not answer in time."""
