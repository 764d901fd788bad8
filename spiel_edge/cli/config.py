"""``spiel-edge config``: the board's stored config (acquisition settings and geometry)."""

from __future__ import annotations

import contextlib
import sys

import click

from spiel_edge.board_config import schema as bc
from spiel_edge.board_config.flash import commit, pull, push
from spiel_edge.cli import EXIT_OK
from spiel_edge.cli._options import board_port, force_option, port_option, profile_option
from spiel_edge.errors import ConfigError, DeviceError
from spiel_edge.profile.schema import load_profile
from spiel_edge.safety.guard import FilePlan, atomic_write
from spiel_edge.safety.shown import escape


def open_session(port: str):
    """The board session (imported here so that the rest of the CLI loads without it)."""
    from spiel_edge.device import DeviceSession

    session = DeviceSession(board_port(port), reconnect=False)
    missing = [
        m
        for m in ("read_config", "write_config", "commit_config", "config_status")
        if not hasattr(session, m)
    ]
    if missing:
        raise DeviceError(
            f"this build's device session lacks {', '.join(missing)}: config transfer unavailable"
        )
    session.open()
    return session


class _Board:
    def __init__(self, port: str):
        self.session = open_session(port)

    def __enter__(self):
        return self.session

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(DeviceError):
            self.session.close()


@click.group("config")
def command() -> None:
    """Pull, show, diff, push and commit the config stored on the board; `template` writes a
    starting config for a new one."""


@command.command("pull")
@port_option
@click.argument("file", required=False, type=click.Path(dir_okay=False))
@force_option
def pull_cmd(port: str, file: str | None, force: bool) -> int:
    """Write the board's active config as TOML to FILE (or stdout)."""
    FilePlan(force).output(file, "FILE")
    with _Board(port) as session:
        config = pull(session)
    if config is None:
        raise DeviceError("the board holds no config yet: `spiel-edge config push` one")
    _write_or_print(file, bc.to_toml(config), f"config of {escape(repr(config['board']['name']))}")
    return EXIT_OK


@command.command("template")
@profile_option
@click.option(
    "--name", default="spiel-board", show_default=True, help="Board name to write into it."
)
@click.argument("file", required=False, type=click.Path(dir_okay=False))
@force_option
def template_cmd(profile_name: str, name: str, file: str | None, force: bool) -> int:
    """A starting config for a new board, from --profile (no board needed): edit it, then
    `config push --port PORT FILE --commit`. Written to FILE, or stdout."""
    FilePlan(force).output(file, "FILE")
    config = bc.from_profile(load_profile(profile_name), name)
    text = f"# a starting board config from profile {profile_name!r}\n{bc.to_toml(config)}"
    text += "" if text.endswith("\n") else "\n"
    _write_or_print(file, text, f"board config {escape(repr(name))}")
    return EXIT_OK


def _write_or_print(file: str | None, text: str, what: str) -> None:
    """TOML to FILE (atomically, then said on stderr) or to stdout."""
    if file and file != "-":
        with atomic_write(file) as fh:
            fh.write(text)
        click.echo(f"{what} written to {escape(file)}", err=True)
    else:
        click.echo(text, nl=False)


@command.command("show")
@port_option
def show_cmd(port: str) -> int:
    """The flash slots, the staging area and the active config."""
    with _Board(port) as session:
        status = session.config_status()
        config = pull(session)
    active = "none (factory defaults)" if status.active_slot == 0xFF else str(status.active_slot)
    click.echo(
        f"# active slot: {active}; staged: {status.staged_length} of {status.max_length} bytes"
    )
    for n in (0, 1):
        valid = getattr(status, f"slot{n}_valid")
        gen, length, crc = (
            getattr(status, f"slot{n}_{k}") for k in ("generation", "length", "crc")
        )
        click.echo(
            f"# slot {n}: "
            + (
                f"generation {gen}, {length} bytes, CRC-32C {crc:08x}"
                if valid
                else "empty or invalid"
            )
        )
    click.echo(bc.to_toml(config) if config else "# no config stored", nl=False)
    return EXIT_OK


def _target(session, file: str, profile_name: str, name: str | None) -> tuple[dict | None, dict]:
    """The board's current config and what it becomes with FILE (full or partial) over it."""
    current = pull(session)
    base = (
        current
        if current is not None
        else bc.from_profile(load_profile(profile_name), name or "spiel-board")
    )
    partial = bc.read_file(file)
    if name:
        partial.setdefault("board", {})["name"] = name
    return current, bc.overlay(base, partial, origin=file)


@command.command("diff")
@port_option
@profile_option
@click.option("--name", default=None, help="Board name to set.")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
def diff_cmd(port: str, profile_name: str, name: str | None, file: str) -> int:
    """What pushing FILE (a board config or a calibration) would change."""
    with _Board(port) as session:
        current, new = _target(session, file, profile_name, name)
    lines = bc.diff(current, new)
    click.echo("\n".join(lines) if lines else "no changes")
    return EXIT_OK


@command.command("push")
@port_option
@profile_option
@click.option("--name", default=None, help="Board name to set.")
@click.option(
    "--commit/--no-commit",
    "do_commit",
    default=False,
    help="Also make it persistent (same as `config commit` afterwards).",
)
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
def push_cmd(port: str, profile_name: str, name: str | None, do_commit: bool, file: str) -> int:
    """Write FILE over the board's config into its staging area, read back and compare.

    FILE is a full board config or a partial one such as a calibration ([geometry] only); a
    board without a config starts from the --profile's values. Nothing is persistent until
    `config commit`.
    """
    with _Board(port) as session:
        current, new = _target(session, file, profile_name, name)
        for line in bc.diff(current, new):
            click.echo(line, err=True)
        size = len(bc.encode(new))
        with click.progressbar(length=size, label="writing", file=sys.stderr) as bar:
            crc = push(session, new, progress=bar.update)
        click.echo(f"staged {size} bytes, CRC-32C {crc:08x}", err=True)
        if do_commit:
            commit(session, crc)
            click.echo("committed", err=True)
    return EXIT_OK


@command.command("commit")
@port_option
@click.option(
    "--crc", default=None, help="Expected CRC-32C (hex) of the staged config, as `push` printed it."
)
def commit_cmd(port: str, crc: str | None) -> int:
    """Make the staged config persistent (two flash slots: a power cut keeps the old one)."""
    try:
        expected = None if crc is None else int(crc, 16)
    except ValueError as exc:
        raise ConfigError(f"--crc must be hexadecimal, got {crc!r}") from exc
    with _Board(port) as session:
        done = commit(session, expected)
    click.echo(f"committed, CRC-32C {done:08x}", err=True)
    return EXIT_OK
