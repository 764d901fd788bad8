"""The SToF-Chirp recording layout (StofNet, Hahne et al., ICASSP 2024): one TDK CH101 in
pulse-echo, a sequence folder of ``NN_envelope_frame.txt`` (one amplitude per line) and
``NN_iq_frame.txt`` (I and Q columns, one row more than the envelope: the last is dropped),
with the dataset's ``sensor_specs.yaml`` above it (board, firmware, rates, temperature) and,
for labelled recordings, ``truth/true_measurement_positions.csv`` (``index,distance,mm``).

One acquisition per frame number, in frame order. A profile with ``signal = "iq"`` reads the
I/Q file ((q, i) pairs interleaved, the pipeline's I/Q layout), any other the envelope file.
:func:`profile_for_specs` picks the built-in profile the specs describe, with the speed of
sound of their temperature (the authors' 331.4 + 0.6 T m/s).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.recordings.spiel_csv import Recording
from spiel_edge.safety.limits import InputLimits, decode_text, read_bytes_bounded

SPECS_NAME = "sensor_specs.yaml"
TRUTH_CSV = Path("truth") / "true_measurement_positions.csv"
_FRAME_RE = re.compile(r"^(\d+)_(envelope|iq)_frame\.txt$")
MAX_SPECS_BYTES = 64 * 1024
SPECS_LEVELS = 3  # the specs sit in the sequence folder or up to this many folders above

# (model, firmware prefix, samples) -> built-in profile
BUILTIN = {("dk-ch101", "gpr_sr_narrow", 128): "dk-ch101-gpr-sr-narrow"}


def is_sequence(folder: str | Path) -> bool:
    folder = Path(folder)
    return folder.is_dir() and any(_FRAME_RE.match(p.name) for p in folder.iterdir())


def frame_numbers(folder: str | Path) -> list[str]:
    """The frame numbers (as written, e.g. "07") of a sequence folder, in frame order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    found = {m.group(1) for p in folder.iterdir() if (m := _FRAME_RE.match(p.name))}
    if not found:
        raise InputError(f"{folder}: no NN_envelope_frame.txt or NN_iq_frame.txt files")
    return sorted(found, key=lambda n: (int(n), n))


def find_specs(folder: str | Path) -> Path | None:
    """``sensor_specs.yaml`` in the folder or up to SPECS_LEVELS folders above it."""
    here = Path(folder).resolve()
    for candidate in [here, *here.parents][: SPECS_LEVELS + 1]:
        if (candidate / SPECS_NAME).is_file():
            return candidate / SPECS_NAME
    return None


def read_specs(path: str | Path) -> dict[str, str]:
    """The ``key: value`` lines of a sensor_specs.yaml (comments and other lines skipped)."""
    path = Path(path)
    data = read_bytes_bounded(path, MAX_SPECS_BYTES, InputError, path.name, "a specs file")
    out: dict[str, str] = {}
    for line in decode_text(data, InputError, path.name).splitlines():
        line = line.split("#", 1)[0].strip()
        key, sep, value = line.partition(":")
        if sep and key.strip() and " " not in key.strip():
            out[key.strip()] = value.strip()
    return out


def profile_for_specs(specs: dict[str, str], origin: str = SPECS_NAME):
    """The built-in profile of the board the specs describe, its speed of sound from their
    temperature; ConfigError naming what did not match (then give --profile)."""
    from spiel_edge.profile.schema import load_profile

    model = specs.get("model", "").lower()
    firmware = specs.get("firmware", "").lower()
    try:
        samples = int(specs.get("DATA_MAX_NUM_SAMPLES", "0"))
    except ValueError:
        samples = 0
    name = next(
        (
            n
            for (m, f, s), n in BUILTIN.items()
            if m == model and firmware.startswith(f) and s == samples
        ),
        None,
    )
    if name is None:
        raise ConfigError(
            f"{origin}: no built-in profile for model {model!r}, firmware {firmware!r}, "
            f"{samples} samples; give --profile"
        )
    profile = load_profile(name)
    acq = profile.acquisition
    for key, have in (("fhz_sample", acq.sample_rate_hz), ("fhz_carrier", acq.carrier_hz)):
        if key in specs and abs(_number(specs[key], key, origin) - have) > 0.5:
            raise ConfigError(
                f"{origin}: {key} {specs[key]} differs from profile {name}'s {have:g}"
            )
    if "temperature" in specs:
        celsius = _number(specs["temperature"].split()[0], "temperature", origin)
        geometry = dataclasses.replace(profile.geometry, speed_of_sound_m_s=331.4 + 0.6 * celsius)
        profile = profile.replace(geometry=geometry)
    return profile


def _number(text: str, key: str, origin: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ConfigError(f"{origin}: {key} is not a number: {text!r}") from None


def read_stof_frame(
    folder: Path, number: str, iq: bool, limits: InputLimits | None = None
) -> np.ndarray:
    """One frame: (1, n) envelope, or (1, 2 n) (q, i) pairs from the I/Q file."""
    limits = limits or InputLimits()
    name = f"{number}_{'iq' if iq else 'envelope'}_frame.txt"
    path = folder / name
    data = read_bytes_bounded(path, limits.max_text_bytes, InputError, name, "a frame")
    rows = [
        line.split() for line in decode_text(data, InputError, name).splitlines() if line.strip()
    ]
    width = 2 if iq else 1
    if not rows or any(len(r) != width for r in rows):
        raise InputError(f"{name}: expected {width} column(s) per line")
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:
        raise InputError(f"{name}: not numeric") from None
    if not np.all(np.isfinite(values)):
        raise InputError(f"{name}: contains NaN or infinite samples")
    if not iq:
        return values.T.copy()
    values = values[:-1] if len(values) > 1 else values  # one row more than the envelope
    out = np.empty((1, 2 * len(values)))
    out[0, 0::2], out[0, 1::2] = values[:, 1], values[:, 0]  # columns I, Q -> (q, i) pairs
    return out


def iter_stof_recordings(
    folder: str | Path, iq: bool, limits: InputLimits | None = None
) -> Iterator[Recording]:
    """Each frame of a sequence folder in frame order; read errors become Recording.error."""
    folder = Path(folder)
    for number in frame_numbers(folder):
        try:
            frames = read_stof_frame(folder, number, iq, limits)
        except InputError as exc:
            yield Recording(number, None, None, str(exc))
            continue
        yield Recording(number, frames, None)


def sequence_folders(root: str | Path) -> list[Path]:
    """A sequence folder itself, or the sequence folders one or two levels under a dataset
    folder (``train/<d>/``, ``<d>/``; ``truth/`` left out), in name order (numbers as numbers).
    No deeper: a wrong path is refused quickly, not walked."""
    root = Path(root)
    if is_sequence(root):
        return [root]
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    found = []
    for child in sorted(p for p in root.iterdir() if p.is_dir() and p.name != "truth"):
        if is_sequence(child):
            found.append(child)
            continue
        found.extend(
            p for p in child.iterdir() if p.is_dir() and p.name != "truth" and is_sequence(p)
        )
    found.sort(key=lambda p: [int(s) if s.isdigit() else s for s in p.relative_to(root).parts])
    if not found:
        raise InputError(f"{root}: no SToF-Chirp sequence folders (NN_envelope_frame.txt files)")
    return found


def truth_mm(sequence: str | Path) -> float | None:
    """The labelled distance (mm) of a sequence folder <d>, from the dataset's
    truth/true_measurement_positions.csv beside its specs; None when there is none."""
    sequence = Path(sequence)
    specs = find_specs(sequence)
    if specs is None or not sequence.name.isdigit():
        return None
    table = specs.parent / TRUTH_CSV
    if not table.is_file():
        return None
    text = decode_text(
        read_bytes_bounded(table, MAX_SPECS_BYTES, InputError, table.name, "a truth table"),
        InputError,
        table.name,
    )
    for line in text.splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) >= 2 and parts[0].isdigit() and int(parts[0]) == int(sequence.name):
            try:
                return float(parts[1])
            except ValueError:
                return None
    return None
