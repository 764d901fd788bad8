"""Python-version shims: spiel-edge supports Python 3.10 (Ubuntu 22.04 / ROS 2 Humble, JetPack 6).

``tomllib`` is stdlib from 3.11; on 3.10 the same API comes from ``tomli`` (a dependency on
3.10 only, by environment marker in pyproject.toml).
"""

from __future__ import annotations

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

__all__ = ["tomllib"]
