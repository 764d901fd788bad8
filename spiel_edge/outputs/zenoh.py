"""Fleet publishing over Zenoh (extra ``zenoh``): each record as JSON on one key expression.

The session uses Zenoh's own configuration: a JSON5 file given here, or ``$ZENOH_CONFIG``,
else the defaults (peer mode). Nothing is reachable beyond this computer unless asked
(docs/security.md): what neither the options nor the file set is confined by
:func:`confine_to_loopback` (listen on loopback only, no multicast scouting).
Congestion control drops records rather than blocking the run loop.
"""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path
from typing import Any

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.sink import Sink

log = logging.getLogger(__name__)


_RUST_SOURCE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


_SECRETS: set[str] = set()  # the user-password values of configurations loaded here
_SECRET_PATHS = ("transport/auth/usrpwd/user", "transport/auth/usrpwd/password")


def zenoh_reason(exc: BaseException) -> str:
    """A Zenoh error's text without the Rust source location it carries (``timeout at
    /root/.cargo/.../orchestrator.rs:1253.`` -> ``timeout``), on one line, with any user or
    password of a loaded configuration replaced by ``***``."""
    text = _RUST_SOURCE.sub("", str(exc)).replace("\\n", " ")
    for secret in _SECRETS:
        text = text.replace(secret, "***")
    return " ".join(text.split()) or type(exc).__name__


def _remember_secrets(cfg) -> None:
    for path in _SECRET_PATHS:
        try:
            value = json.loads(cfg.get_json(path))
        except Exception:  # zenoh.ZError: not set in this Zenoh's schema
            continue
        if isinstance(value, str) and len(value) >= 3:
            _SECRETS.add(value)


_WHERE = re.compile(r"line:\s*(\d+),\s*column:\s*(\d+)|-->\s*(\d+):(\d+)")
_UNKNOWN_KEY = re.compile(r"unknown field `([A-Za-z0-9_]{1,64})`")
_EXPECTED = re.compile(
    r"expected ((?:one of )?`[A-Za-z0-9_-]{1,32}`(?:, `[A-Za-z0-9_-]{1,32}`)*|[a-z0-9 ]{1,40}?)(?=[\",]|$)"
)


def config_reason(exc: BaseException) -> str:
    """Why Zenoh refused a configuration file, in words that never quote the file: Zenoh's
    own message may show the offending line or value (a password, a key), so only the
    location, an unknown key's name and what the schema expected are kept."""
    text = str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    where = _WHERE.search(text)
    at = f" at line {where[1] or where[3]}, column {where[2] or where[4]}" if where else ""
    if m := _UNKNOWN_KEY.search(text):
        return f"unknown key {m[1]!r}{at}"
    expected = _EXPECTED.search(text)
    hint = f" (expected {expected[1].strip()})" if expected else ""
    if "invalid type" in text or "invalid value" in text or "unknown variant" in text:
        return f"a value Zenoh does not take{at}{hint}; values are not shown"
    if "-->" in text or "expected" in text:
        return f"not valid JSON5{at}; values are not shown"
    if "No such file" in text or "not found" in text.lower():
        return "no such file"
    return f"not a Zenoh configuration{at}; its text is not shown"


def import_zenoh():
    try:
        import zenoh
    except ImportError as exc:
        raise ConfigError(f"--zenoh needs Zenoh: pip install 'spiel-edge[zenoh]' ({exc})") from exc
    return zenoh


def load_config(config: Any = None):
    """A zenoh.Config from a Config, a JSON5 file path, ``$ZENOH_CONFIG`` or the defaults."""
    zenoh = import_zenoh()
    if isinstance(config, zenoh.Config):
        return config
    path = config or os.environ.get("ZENOH_CONFIG")
    if not path:
        return zenoh.Config()
    try:
        cfg = zenoh.Config.from_file(str(Path(path)))
    except Exception as exc:  # zenoh.ZError and I/O errors alike: never echo the file
        raise ConfigError(f"Zenoh config {path}: {config_reason(exc)}") from None
    _remember_secrets(cfg)
    return cfg


LOOPBACK_LISTEN = ("tcp/127.0.0.1:0",)  # a peer's default listener: this computer only


def confine_to_loopback(cfg) -> None:
    """What the configuration leaves at Zenoh's defaults, confined to this computer: a peer
    listens on loopback (Zenoh's default: ``tcp/[::]:0``, every interface) and does not scout by
    multicast (Zenoh's default: on, 224.0.0.224:7446 on every interface). A listen endpoint or a
    scouting setting given (option or file) is kept as given."""
    if isinstance(json.loads(cfg.get_json("listen/endpoints")), dict):  # per-mode: the default
        cfg.insert_json5("listen/endpoints", json.dumps(list(LOOPBACK_LISTEN)))
    if json.loads(cfg.get_json("scouting/multicast/enabled")) is None:
        cfg.insert_json5("scouting/multicast/enabled", "false")


# proto/HOST:PORT (HOST a name, IPv4 or [IPv6]), optional ?metadata or #config; or a socket path
_ENDPOINT = re.compile(
    r"(?:tcp|udp|tls|quic|ws)/(?:\[[0-9A-Fa-f:.]+(?:%\w+)?\]|[A-Za-z0-9_.-]+)"
    r":(?P<port>\d{1,5})(?:[?#]\S*)?|unixsock-stream/\S+"
)


def check_endpoint(endpoint: str) -> str:
    """A Zenoh locator such as ``tcp/127.0.0.1:7447`` (ConfigError naming --zenoh-connect)."""
    m = _ENDPOINT.fullmatch(endpoint or "")
    if not m or (m["port"] is not None and not 1 <= int(m["port"]) <= 65535):
        raise ConfigError(
            f"--zenoh-connect {endpoint!r}: expected a Zenoh endpoint such as tcp/HOST:7447 "
            "(a port 1-65535; an IPv6 address in brackets)"
        )
    return endpoint


def session_config(config: Any = None, settings: Any = None, *, rmw_zenoh: bool = False):
    """The session's configuration: ``config`` (or $ZENOH_CONFIG, or the defaults) with the
    mode and endpoints of ``settings`` (outputs.ros2.ZenohSettings) over it, confined to
    loopback where neither sets otherwise (:func:`confine_to_loopback`; rmw_zenoh's own
    sessions listen on ``tcp/localhost:0`` and do not scout by multicast either)."""
    zenoh = import_zenoh()
    del rmw_zenoh  # every encoding is confined alike
    if config is None:
        config = getattr(settings, "config_file", None)
    cfg = load_config(config)
    try:
        if settings is not None and settings.mode:
            cfg.insert_json5("mode", json.dumps(settings.mode))
        if settings is not None and settings.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
        confine_to_loopback(cfg)
    except Exception as exc:  # zenoh.ZError
        raise ConfigError(f"--zenoh: bad Zenoh setting: {zenoh_reason(exc)}") from exc
    del zenoh
    return cfg


def publish_key_problem(key: str) -> str | None:
    """Why ``key`` cannot be a key records are published on (None when it can): a concrete
    Zenoh key, chunks between single slashes, no wildcard (``*``, ``$*``) or reserved
    character (``?``, ``#``); a wildcard would reach other publishers' subscribers."""
    if not key:
        return "is empty"
    if key.startswith("/") or key.endswith("/") or "//" in key:
        return "has an empty chunk (a leading, trailing or double '/')"
    for bad, what in (("*", "a wildcard"), ("$", "a wildcard"), ("?", "'?'"), ("#", "'#'")):
        if bad in key:
            return f"holds {what}: records go out on one concrete key"
    if any(c.isspace() for c in key):
        return "holds white space"
    return None


def open_publishers(keys: dict[str, str], encoding: str, config: Any = None, settings: Any = None):
    """(session, {name: publisher}) for the key expressions ``keys``; ``encoding`` names a
    ``zenoh.Encoding`` attribute. Bad keys or an unreachable network: ConfigError."""
    zenoh = import_zenoh()
    exprs = {}
    for name, key in keys.items():
        if problem := publish_key_problem(key):
            raise ConfigError(f"--zenoh {key!r} {problem}")
        try:
            exprs[name] = zenoh.KeyExpr(key)
        except Exception as exc:
            raise ConfigError(
                f"--zenoh {key!r} is not a valid key expression: {zenoh_reason(exc)}"
            ) from exc
    try:
        session = zenoh.open(session_config(config, settings))
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(
            f"--zenoh: cannot open a Zenoh session ({zenoh_reason(exc)}): in client mode a "
            "router must be reachable at the endpoints given"
            if getattr(settings, "mode", "") == "client"
            else f"--zenoh: cannot open a Zenoh session: {zenoh_reason(exc)}"
        ) from exc
    publishers = {
        name: session.declare_publisher(
            expr,
            encoding=getattr(zenoh.Encoding, encoding),
            congestion_control=zenoh.CongestionControl.DROP,  # drop, never block the run loop
        )
        for name, expr in exprs.items()
    }
    return session, publishers


class ZenohSink(Sink):
    """Publish each record on ``key_expr`` (e.g. ``robots/r1/spiel/position``), tagged when
    the settings carry a board's key (outputs/record_auth.py)."""

    _auth_key: bytes | None = None

    def __init__(self, key_expr: str, config: Any = None, settings: Any = None):
        self._session, publishers = open_publishers(
            {"record": key_expr}, "APPLICATION_JSON", config, settings
        )
        self._publisher = publishers["record"]
        self.key_expr = key_expr
        self._auth_key = getattr(settings, "auth_key", None)
        self.failed = 0
        log.info("publishing records on Zenoh key %s", self.key_expr)

    def write(self, record: dict) -> None:
        try:
            payload = json.dumps(record, separators=(",", ":"), allow_nan=False).encode()
            if self._auth_key is None:
                self._publisher.put(payload)
            else:
                from spiel_edge.outputs.record_auth import attachment

                tag = attachment(self._auth_key, self.key_expr, payload)
                self._publisher.put(payload, attachment=tag)
        except Exception as exc:  # zenoh.ZError: keep the run going, like UDP
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                log.warning(
                    "Zenoh put on %s failed (%d so far): %s", self.key_expr, self.failed, exc
                )

    _closed = False

    def close(self) -> None:
        """Undeclare and close the session; safe to call again (zenoh refuses a second
        undeclare)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._publisher.undeclare()
        finally:
            self._session.close()
