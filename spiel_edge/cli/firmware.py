"""``spiel-edge firmware``: the board's firmware slots; update with rollback (protocol 2)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from spiel_edge.cli import EXIT_ERROR, EXIT_OK
from spiel_edge.cli._options import board_port, force_option, port_option
from spiel_edge.errors import DeviceError, InputError
from spiel_edge.io.guard import FilePlan, atomic_write
from spiel_edge.io.shown import escape  # a board's or an image's strings: never raw

MAX_IMAGE_BYTES = 64 * 1024 * 1024  # an image file larger than this is refused unread


def _open(port: str | None):
    from spiel_edge.device import DeviceSession

    session = DeviceSession(board_port(port), reconnect=False)
    session.open()
    return session


def _read_image(path: str) -> bytes:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: not a regular file")
    if p.stat().st_size > MAX_IMAGE_BYTES:
        raise InputError(
            f"{path}: {p.stat().st_size} bytes is more than any image ({MAX_IMAGE_BYTES})"
        )
    return p.read_bytes()


@click.group("firmware")
def command() -> None:
    """The board's firmware: info, update (test boot, then confirm) and confirm."""


@command.command("info")
@port_option
def info_cmd(port: str) -> int:
    """The firmware slots, the running image and its boot state."""
    from spiel_edge.device.firmware import describe_info, firmware_info

    session = _open(port)
    try:
        info = firmware_info(session)
        for line in describe_info(info, session.hello):
            click.echo(escape(line))
    finally:
        with contextlib.suppress(DeviceError):
            session.close()
    return EXIT_OK


@command.command("update")
@port_option
@click.argument("image", type=click.Path(dir_okay=False))
@click.option(
    "--wait",
    "wait_s",
    type=click.FloatRange(min=0.0, min_open=True, max=3600.0),
    default=20.0,
    show_default=True,
    help="seconds to wait for the new firmware to answer",
)
def update_cmd(port: str, image: str, wait_s: float) -> int:
    """Write IMAGE into the inactive slot, boot it once and confirm it once it answers HELLO;
    a firmware that does not answer is rolled back by the board at its next reset."""
    from spiel_edge.device.firmware import check_image, update_firmware

    data = _read_image(image)
    header = check_image(data)  # refused before the port is opened
    url = board_port(port)
    click.echo(
        f"{escape(image)}: firmware {escape(header.version)} for {escape(header.target)}, "
        f"{len(data)} bytes",
        err=True,
    )

    line_open = [False]

    def progress(sent: int, total: int) -> None:
        line_open[0] = sent < total
        click.echo(f"\r  {sent}/{total} bytes", nl=not line_open[0], err=True)

    try:
        result = update_firmware(url, data, progress=progress, boot_wait_s=wait_s)
    finally:
        if line_open[0]:  # the error goes on a line of its own
            click.echo("", err=True)
    if result.rolled_back:
        click.echo(
            f"the board came back with {escape(result.version)}: firmware "
            f"{escape(header.version)} was rolled "
            "back (it did not answer in time, or the board lost power before its confirmation "
            "was stored)",
            err=True,
        )
        return EXIT_ERROR
    click.echo(
        f"firmware {escape(result.previous)} -> {escape(result.version)}, confirmed "
        f"({result.seconds:.1f} s)",
        err=True,
    )
    return EXIT_OK


@command.command("confirm")
@port_option
def confirm_cmd(port: str) -> int:
    """Keep the running trial image (what `update` does once the new firmware answers)."""
    from spiel_edge.device.firmware import confirm_firmware

    session = _open(port)
    try:
        answer = confirm_firmware(session)
    finally:
        with contextlib.suppress(DeviceError):
            session.close()
    click.echo(f"slot {answer.slot} confirmed")
    return EXIT_OK


@command.command("pack")
@click.argument("body", type=click.Path(dir_okay=False, exists=True))
@click.option("--version", "version", required=True, help="firmware version text (<= 16 bytes)")
@click.option("--target", required=True, help="board target: posix, mps2-an386, sim, ...")
@click.option(
    "--protocol", default="1-2", show_default=True, help="protocol versions it speaks, LOW-HIGH"
)
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False))
@force_option
def pack_cmd(body: str, version: str, target: str, protocol: str, output: str, force: bool) -> int:
    """Wrap a firmware BODY (the target's binary) in an image header.

    For mps2-an386 the BODY is build/mps2/app.bin (make TARGET=mps2), the application linked
    for the boot stage's execution region."""
    from firmware_protocol.image import ImageError, check_body, pack_image

    plan = FilePlan(force)
    plan.input_file(body, "BODY")
    plan.output(output, "--output")
    try:
        low, high = (int(v) for v in protocol.split("-"))
    except ValueError as exc:
        raise InputError(f"--protocol must be LOW-HIGH, e.g. 1-2, got {protocol!r}") from exc
    try:
        raw = _read_image(body)
        check_body(raw, target)
        image = pack_image(raw, version=version, target=target, min_protocol=low, max_protocol=high)
    except (ValueError, ImageError) as exc:
        raise InputError(str(exc)) from exc
    with atomic_write(output, "wb") as fh:
        fh.write(image)
    click.echo(
        f"{escape(output)}: {escape(version)} for {escape(target)}, {len(image)} bytes", err=True
    )
    return EXIT_OK
