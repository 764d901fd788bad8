"""Model weights checked once against onnxruntime, stored so later loads skip onnxruntime.

A model the runtime evaluates in numba (the association MLP, :mod:`spiel_edge.pipeline.learned.mlp`)
is read from its ONNX file and compared with onnxruntime on a probe batch the first time it is
loaded (or at ``spiel-edge warmup`` / ``service install``, or at build time by
``python -m tools.release.verify_models``). What agreed is stored as a small ``.npz`` holding the
weights, the metadata and the SHA-256 of the ONNX file. A later load whose file has the same
hash reads the ``.npz`` and never imports onnxruntime (about 28 MiB and 0.1-0.2 s less per
process, docs/performance.md); a changed or unknown file goes through onnxruntime again.

Looked up, by the file name ``<stem>-<first 16 hex of the hash>.verified.npz``, next to the
model (what a build ships) and in the cache folder: ``SPIEL_EDGE_MODEL_CACHE``, else
``$NUMBA_CACHE_DIR/verified-models`` (the service's cache), else
``$XDG_CACHE_HOME/spiel-edge/verified-models`` (``~/.cache`` by default). Writing is best
effort: a read-only folder only means the check runs again next time.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

SUFFIX = ".verified.npz"


def digest(blob: bytes) -> str:
    return hashlib.sha256(blob).hexdigest()


def cache_dir() -> Path:
    if os.environ.get("SPIEL_EDGE_MODEL_CACHE"):
        return Path(os.environ["SPIEL_EDGE_MODEL_CACHE"])
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"]) / "verified-models"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "spiel-edge" / "verified-models"


def file_name(model_path: Path, sha256: str) -> str:
    return f"{Path(model_path).stem}-{sha256[:16]}{SUFFIX}"


def load(model_path: Path, sha256: str, names: tuple[str, ...]) -> tuple[tuple, dict] | None:
    """``(arrays in names order, metadata)`` stored for this file's hash, or None."""
    name = file_name(model_path, sha256)
    for folder in (Path(model_path).parent, cache_dir()):
        path = folder / name
        if not path.is_file():
            continue
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["sha256"]) != sha256:
                    continue
                arrays = tuple(_contiguous(z[n]) for n in names)
                metadata = json.loads(str(z["metadata"]))
        except (OSError, ValueError, KeyError) as exc:
            log.info("ignoring %s (%s)", path, exc)
            continue
        log.debug("verified weights for %s from %s", model_path, path)
        return arrays, metadata
    return None


def store(
    model_path: Path,
    sha256: str,
    names: tuple[str, ...],
    arrays: tuple,
    metadata: dict,
    folder: Path | None = None,
) -> Path | None:
    """Write the verified arrays atomically (into ``folder``, default the cache folder);
    the path written, or None when the folder is not writable."""
    folder = cache_dir() if folder is None else Path(folder)
    path = folder / file_name(model_path, sha256)
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(
                f,
                sha256=np.array(sha256),
                metadata=np.array(json.dumps(metadata, sort_keys=True)),
                **dict(zip(names, arrays, strict=True)),
            )
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600; the service user reads it
        os.replace(tmp, path)
    except OSError as exc:
        log.info("cannot store verified weights in %s (%s)", folder, exc)
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        return None
    return path


def _contiguous(a: np.ndarray) -> np.ndarray:
    return a if a.ndim == 0 else np.ascontiguousarray(a)  # (ascontiguousarray makes 0-d 1-d)
