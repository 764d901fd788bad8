"""What a recording input is, told by its content (never by its name alone).

The kinds a command takes:

- ``spiel-csv``: a folder of ``*_frames.csv`` files (the published dataset's layout);
- ``mcap``: an MCAP recording (``run --record``, ``replay -o FILE.mcap``);
- ``labelled``: a labelled set, an ``.npz`` with ``frames`` and ``backgrounds`` (M, channels,
  samples), ``truth_mm`` (M, 3) and ``names`` (M,): the vendored
  ``spiel_edge/data/spiel_icra23_subset.npz``;
- ``stof-chirp``: a SToF-Chirp sequence folder (told apart by its file names in
  :mod:`spiel_edge.recordings.stof_chirp`; listed here for the messages);
- ``scenes``: a scene file, the same with ``truth_mm`` (M, targets, 3) (tools/train/build_scenes.py).

Anything else is one :class:`InputError` line saying what the file is and what was expected.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from spiel_edge.errors import InputError
from spiel_edge.safety.shown import shorten

MCAP_MAGIC = b"\x89MCAP0\r\n"
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a member first, or an empty archive
NPY_MAGIC = b"\x93NUMPY"
RECORDING_KINDS = ("spiel-csv", "mcap", "labelled", "scenes")
EXPECTED = (
    "a spiel-csv folder, an MCAP recording, or a labelled .npz "
    "(frames, backgrounds, truth_mm, names: spiel_edge/data/spiel_icra23_subset.npz)"
)


def sniff(path: str | Path) -> str:
    """``folder``, ``mcap``, ``npz``, ``npy``, ``empty`` or ``other`` from the first bytes;
    InputError when it cannot be read or is not a regular file."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise InputError(f"{shorten(path)}: cannot read: {exc.strerror}") from None
    if stat.S_ISDIR(st.st_mode):
        return "folder"
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{shorten(path)}: not a regular file or folder")
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise InputError(f"{shorten(path)}: cannot read: {exc.strerror}") from None
    if not head:
        return "empty"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(ZIP_MAGIC):
        return "npz"
    if head.startswith(NPY_MAGIC):
        return "npy"
    return "other"


def recording_kind(path: str | Path, accepted: tuple[str, ...] = RECORDING_KINDS) -> str:
    """The kind of recording at ``path`` (one of ``accepted``), from its content; one
    InputError line otherwise, naming what it is and what the command takes."""
    path = Path(path)
    found = sniff(path)
    if path.suffix == ".mcap" and found != "mcap" and "mcap" in accepted:
        raise InputError(f"{shorten(path)}: not an MCAP file (no MCAP magic at its start)")
    if found == "npz":
        found = _npz_kind(path)
    elif found == "folder":
        found = "spiel-csv"
    if found in accepted:
        return found
    what = {
        "empty": "an empty file",
        "npy": "a single .npy array (a background capture?)",
        "other": "not a recording",
        "npz-other": "an .npz archive without frames, backgrounds, truth_mm and names",
        "spiel-csv": "a folder",
        "mcap": "an MCAP recording",
        "labelled": "a labelled .npz set",
        "scenes": "a scene file (.npz)",
    }[found]
    raise InputError(f"{shorten(path)}: {what}; expected {_expected(accepted)}")


def _expected(accepted: tuple[str, ...]) -> str:
    names = {
        "spiel-csv": "a spiel-csv folder",
        "mcap": "an MCAP recording",
        "labelled": "a labelled .npz (spiel_edge/data/spiel_icra23_subset.npz)",
        "scenes": "a scene file (.npz with truth_mm per target)",
        "stof-chirp": "a SToF-Chirp sequence folder (NN_envelope_frame.txt)",
    }
    parts = [names[k] for k in accepted]
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " or " + parts[-1]


def _npz_kind(path: Path) -> str:
    from spiel_edge.safety.limits import load_npz_bounded

    heads = load_npz_bounded(path, "scenes", headers_only=True, text_ok=True)
    if not {"frames", "backgrounds", "truth_mm", "names"} <= set(heads):
        return "npz-other"
    ndim = len(heads["truth_mm"][0])
    return {2: "labelled", 3: "scenes"}.get(ndim, "npz-other")
