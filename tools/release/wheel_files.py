"""The files of a release wheel: numba's platform tag, the kernels' manifest, the wheel
re-tagged with its kernels and a RECORD pip accepts (used by ``build_wheels``)."""

from __future__ import annotations

import base64
import csv
import hashlib
import io
import json
import zipfile
from pathlib import Path

KERNELS = "spiel_edge/_kernels"


def platform_tag(wheel_metadata: str) -> str:
    """The platform part of numba's wheel tag (e.g. manylinux_2_17_x86_64.manylinux2014_x86_64)."""
    platforms = []
    for line in wheel_metadata.splitlines():
        if line.startswith("Tag:"):
            platform = line.split(":", 1)[1].strip().split("-")[-1]
            if platform not in platforms:
                platforms.append(platform)
    if not platforms:
        raise SystemExit("numba's wheel names no platform tag: is numba installed from a wheel?")
    return ".".join(platforms)


def manifest(kernels: Path, ident: dict) -> dict:
    files = {
        p.relative_to(kernels).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(kernels.rglob("*"))
        if p.is_file() and p.suffix in (".nbi", ".nbc", ".nbo")  # .nbo: numba's runtime
    }
    keep = ("python", "machine", "numba", "llvmlite")
    return {**{k: ident[k] for k in keep}, "cpu": "generic", "files": files}


def package(pure: Path, kernels: Path, ident: dict, out: Path) -> Path:
    """The pure wheel plus the kernels and manifest, re-tagged for this Python and platform."""
    py = ident["python"].replace("cpython-", "cp")
    name, version = pure.name.split("-")[:2]
    target = out / f"{name}-{version}-{py}-{py}-{ident['platform']}.whl"
    info = f"{name}-{version}.dist-info"
    added = {
        f"{KERNELS}/{rel}": (kernels / rel).read_bytes()
        for rel in manifest(kernels, ident)["files"]
    }
    added[f"{KERNELS}/manifest.json"] = (
        json.dumps(manifest(kernels, ident), indent=1) + "\n"
    ).encode()
    records = []
    out.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(pure) as src, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.infolist():
            if item.filename in (f"{info}/RECORD",):
                continue
            data = src.read(item.filename)
            if item.filename == f"{info}/WHEEL":
                data = _retag(data.decode(), py, ident["platform"]).encode()
            dst.writestr(item, data)
            records.append(_record(item.filename, data))
        for path, data in sorted(added.items()):
            dst.writestr(path, data)
            records.append(_record(path, data))
        body = io.StringIO()
        writer = csv.writer(body, lineterminator="\n")
        writer.writerows(records + [(f"{info}/RECORD", "", "")])
        dst.writestr(f"{info}/RECORD", body.getvalue())
    return target


def _retag(wheel_file: str, py: str, platform: str) -> str:
    lines = [
        ln for ln in wheel_file.splitlines() if not ln.startswith(("Tag:", "Root-Is-Purelib:"))
    ]
    lines.append("Root-Is-Purelib: false")
    lines += [f"Tag: {py}-{py}-{p}" for p in platform.split(".")]
    return "\n".join(lines) + "\n"


def _record(path: str, data: bytes) -> tuple[str, str, str]:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return path, f"sha256={digest}", str(len(data))
