"""The record of one acquisition, as every command writes it (the README's record schema):
the pipeline's result, or the error that kept the acquisition from being processed."""

from __future__ import annotations

REASON_INPUT_ERROR = "input error"


def error_record(message: str) -> dict:
    """The fields of a record whose acquisition could not be processed."""
    return {
        "position_mm": None,
        "reason": REASON_INPUT_ERROR,
        "residual_mm": None,
        "echoes": [],
        "matched": [],
        "targets": [],
        "error": message,
    }
