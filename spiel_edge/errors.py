"""The exception root of spiel-edge; every error the package raises derives from SpielError."""


class SpielError(Exception):
    """Root of all spiel-edge errors."""


class ConfigError(SpielError, ValueError):
    """A profile, calibration or config file is invalid (the message names the key)."""


class InputError(SpielError, ValueError):
    """An acquisition or recording is malformed (the message names the file)."""


class OutputError(SpielError, OSError):
    """Every output of a command failed (disk full, folder gone, ...): nothing more is kept."""


class ModelError(SpielError):
    """The association model is missing or unusable."""


class DeviceError(SpielError, OSError):
    """The board is missing, unplugged or misbehaving."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The board did not answer in time."""


class DeviceDisconnectedError(DeviceError):
    """The link to the board went away (unplugged, reset, pty closed): reconnect may help."""


class DeviceRequestError(DeviceError):
    """The board answered a request with an error (``code``: spiel_edge.protocol.ErrorCode)."""

    def __init__(self, message: str, code: int = 0, request_type: int = 0) -> None:
        super().__init__(message)
        self.code = code
        self.request_type = request_type
