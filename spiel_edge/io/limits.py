"""How large an input may be before it is parsed: derived from the profile's frame shape, so
a hostile or damaged file costs at most about one frame's worth of memory."""

from __future__ import annotations

from dataclasses import dataclass

from spiel_edge.errors import InputError

MAX_VALUE_CHARS = 32  # one sample as text, separator included ("-1.2345678901234567e+308 ")
OVERHEAD_BYTES = 64 * 1024  # metadata beside the samples (MCAP JSON) or blank lines (csv)
GENERIC_CHANNELS, GENERIC_SAMPLES = 64, 16384  # when no profile says otherwise


@dataclass(frozen=True)
class InputLimits:
    max_channels: int = GENERIC_CHANNELS
    max_samples: int = GENERIC_SAMPLES

    @classmethod
    def for_profile(cls, profile) -> InputLimits:
        """The profile's frame shape (a little slack, so a wrong shape still gets its own
        clear error naming both shapes)."""
        channels = len(profile.geometry.channels_mm)
        samples = int(profile.acquisition.n_samples)
        return cls(max(2 * channels, 8), max(2 * samples, 64))

    @property
    def max_values(self) -> int:
        return self.max_channels * self.max_samples

    @property
    def max_text_bytes(self) -> int:
        return self.max_values * MAX_VALUE_CHARS + OVERHEAD_BYTES

    @property
    def max_json_bytes(self) -> int:
        return self.max_text_bytes

    def check_shape(self, channels: int, samples: int) -> None:
        if channels > self.max_channels or samples > self.max_samples:
            raise InputError(
                f"{channels} channels x {samples} samples exceed the profile's bound of "
                f"{self.max_channels} x {self.max_samples}"
            )
