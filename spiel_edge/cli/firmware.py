"""``spiel-edge firmware``: the board's firmware slots; update with rollback (protocol 2)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from spiel_edge.cli import EXIT_ERROR, EXIT_OK
from spiel_edge.cli._options import board_port, force_option, port_option
from spiel_edge.errors import DeviceError, InputError
from spiel_edge.safety.guard import FilePlan, atomic_write
from spiel_edge.safety.shown import escape  # a board's or an image's strings: never raw

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
    """Write IMAGE into the inactive slot, boot it once and confirm it once its self-test
    passed, on the same board (serial and target checked). Prints the state the board reports
    after: confirmed (exit 0), rolled back, or still on trial. A trial an interrupted update
    left is finished (the same image) or rolled back first."""
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
    on_terminal = click.get_text_stream("stderr").isatty()
    quarters = [0]  # a log file gets a line at each quarter, not a \r per chunk

    def progress(sent: int, total: int) -> None:
        if not on_terminal:
            quarter = 4 * sent // total if total else 4
            if quarter > quarters[0]:
                quarters[0] = quarter
                click.echo(f"  {sent}/{total} bytes", err=True)
            return
        line_open[0] = sent < total
        click.echo(f"\r  {sent}/{total} bytes", nl=not line_open[0], err=True)

    try:
        result = update_firmware(url, data, progress=progress, boot_wait_s=wait_s)
    finally:
        if line_open[0]:  # the error goes on a line of its own
            click.echo("", err=True)
    click.echo(update_outcome_line(result, header.version), err=True)
    return EXIT_OK if result.confirmed else EXIT_ERROR


def update_outcome_line(result, version: str) -> str:
    """One line: what the board reports after the update (its slot, version and state)."""
    from spiel_edge.safety.shown import escape

    state = f"board {escape(result.serial)} runs {escape(result.version)} in slot {result.slot}"
    if result.confirmed:
        return (
            f"firmware {escape(result.previous)} -> {escape(result.version)}, confirmed: "
            f"{state} ({result.seconds:.1f} s)"
        )
    if result.rolled_back:
        return f"firmware {escape(version)} was rolled back: {result.reason}; {state}, confirmed"
    return (
        f"firmware {escape(version)} is NOT confirmed ({result.reason}): {state} on trial; it "
        "rolls back by itself unless `spiel-edge firmware confirm` keeps it"
    )


@command.command("confirm")
@port_option
def confirm_cmd(port: str) -> int:
    """Keep the running trial image (what `update` does once its self-test passed; the board
    refuses before)."""
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
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False),
    help="The image file to write (for `firmware update IMAGE`).",
)
@click.option(
    "--key",
    "key_path",
    type=click.Path(dir_okay=False),
    help="private key to sign with (keygen's KEY.key; needs the 'sign' extra). Boards refuse "
    "unsigned images",
)
@click.option(
    "--security-counter",
    type=click.IntRange(0, 0xFFFF_FFFF),
    default=0,
    show_default=True,
    help="anti-rollback counter: a board that confirmed an image with a higher one refuses this",
)
@click.option("--release", is_flag=True, help="refuse the development key")
@force_option
def pack_cmd(
    body: str,
    version: str,
    target: str,
    protocol: str,
    output: str,
    key_path: str | None,
    security_counter: int,
    release: bool,
    force: bool,
) -> int:
    """Wrap a firmware BODY (the target's binary) in an image header, signed with --key.

    For mps2-an386 the BODY is build/mps2/app.bin (make TARGET=mps2), the application linked
    for the boot stage's execution region."""
    from spiel_edge.device.fwkeys import is_dev_key, load_private_key
    from spiel_edge.protocol.image import ImageError, check_body, pack_image

    plan = FilePlan(force)
    plan.input_file(body, "BODY")
    if key_path is not None:
        plan.input_file(key_path, "--key")
    plan.output(output, "--output")
    try:
        low, high = (int(v) for v in protocol.split("-"))
    except ValueError as exc:
        raise InputError(f"--protocol must be LOW-HIGH, e.g. 1-2, got {protocol!r}") from exc
    if key_path is None and release:
        raise InputError("--release needs --key: a release image is signed")
    signer = load_private_key(key_path) if key_path is not None else None
    if signer is not None and is_dev_key(signer.public_key) and release:
        raise InputError(f"--key {key_path}: the development key; --release refuses it")
    try:
        raw = _read_image(body)
        check_body(raw, target)
        image = pack_image(
            raw,
            version=version,
            target=target,
            min_protocol=low,
            max_protocol=high,
            security_counter=security_counter,
            signer=signer,
        )
    except (ValueError, ImageError) as exc:
        raise InputError(str(exc)) from exc
    with atomic_write(output, "wb") as fh:
        fh.write(image)
    if signer is None:
        how = "UNSIGNED: boards refuse it (FW_UNSIGNED); sign with --key"
    elif is_dev_key(signer.public_key):
        how = f"signed with the DEVELOPMENT key {signer.key_id}"
    else:
        how = f"signed with key {signer.key_id}"
    click.echo(
        f"{escape(output)}: {escape(version)} for {escape(target)}, security counter {security_counter}, "
        f"{len(image)} bytes, {how}",
        err=True,
    )
    return EXIT_OK


@command.command("check")
@click.argument("image", type=click.Path(dir_okay=False))
@click.option(
    "--pub",
    "pub_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="the public key file a board is built with (keygen's NAME.pub)",
)
@click.option(
    "--min-counter",
    type=click.IntRange(0, 0xFFFF_FFFF),
    default=0,
    show_default=True,
    help="the board's security counter",
)
def check_cmd(image: str, pub_path: str, min_counter: int) -> int:
    """Check IMAGE offline as a board built with --pub would at FW_VERIFY: intact, signed by
    that key, its security counter at least --min-counter (exit 0), or say why not (exit 2)."""
    from spiel_edge.protocol.image import ImageError, verify_image
    from spiel_edge.protocol.signing import parse_public_key_text

    plan = FilePlan(False)
    plan.input_file(image, "IMAGE")
    plan.input_file(pub_path, "--pub")
    try:
        public = parse_public_key_text(Path(pub_path).read_text(errors="replace"))
    except (OSError, ValueError) as exc:
        raise InputError(f"--pub {escape(pub_path)}: {exc}") from exc
    try:
        header = verify_image(_read_image(image), public, min_counter)
    except ImageError as exc:
        code = getattr(exc, "code", None)
        raise InputError(
            f"{escape(image)}: {exc}" + (f" ({code.name})" if code is not None else "")
        ) from exc
    click.echo(
        f"{escape(image)}: firmware {escape(header.version)} for {escape(header.target)}, "
        f"security counter "
        f"{header.security_counter}, signed by key {header.key_id.hex()}: a board with this key "
        "accepts it",
        err=True,
    )
    return EXIT_OK


@command.command("keygen")
@click.argument("name", type=click.Path(dir_okay=False))
@force_option
def keygen_cmd(name: str, force: bool) -> int:
    """Make a signing key pair: NAME.key (private, mode 0600: keep it off the robot) and
    NAME.pub (the public key; build the boot stage with make FW_KEY=NAME.pub)."""
    from spiel_edge.device.fwkeys import generate_key

    private, public = Path(name + ".key"), Path(name + ".pub")
    plan = FilePlan(force)
    plan.output(private, "NAME.key")
    plan.output(public, "NAME.pub")
    if force:
        private.unlink(missing_ok=True)  # written anew with O_EXCL and mode 0600
    try:
        key = generate_key(private, public)
    except OSError as exc:
        raise InputError(f"{escape(name)}: cannot write the key ({exc.strerror or exc})") from exc
    click.echo(f"{escape(private)}: private key (mode 0600), key id {key.key_id}", err=True)
    click.echo(
        f"{escape(public)}: public key: make -C firmware_protocol/firmware FW_KEY={escape(public)}",
        err=True,
    )
    return EXIT_OK
