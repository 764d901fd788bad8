"""``spiel-edge service``: install the systemd unit, udev rule and /etc/spiel-edge config."""

from __future__ import annotations

from pathlib import Path

import click

from spiel_edge.errors import ConfigError
from spiel_edge.service import kit as service_kit


@click.group("service")
def command() -> None:
    """The systemd service kit (unit, service user, udev rule, config)."""


@command.command("install")
@click.option(
    "--prefix",
    default="/",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Root to write under (e.g. a staging folder or an image being built).",
)
@click.option(
    "--exec",
    "exec_path",
    default=None,
    help="spiel-edge executable for ExecStart (default: the one beside this Python).",
)
@click.option(
    "--allow-ip",
    multiple=True,
    metavar="NETWORK",
    help="Besides localhost, a network the service may reach (IPAddressAllow=, e.g. "
    "192.168.1.0/24 for Zenoh to the robot's other computers); repeatable.",
)
@click.option("--dry-run", is_flag=True, help="Print the files and commands; write nothing.")
@click.option(
    "--warmup/--no-warmup",
    default=None,
    help="Compile the kernels into the service's numba cache [default: on when PREFIX is /].",
)
def install(
    prefix: str,
    exec_path: str | None,
    allow_ip: tuple[str, ...],
    dry_run: bool,
    warmup: bool | None,
) -> int:
    """Write the kit under PREFIX; an existing spiel-edge.env is kept. Prints what to run next."""
    from spiel_edge.service.sandbox import protect_home_for

    exec_path = exec_path or service_kit.default_exec()
    live = Path(prefix).resolve() == Path("/")  # the system itself, not a staging folder
    try:
        protect_home = protect_home_for(exec_path)  # under /tmp: the unit could not start
    except ConfigError as exc:
        if live:
            raise
        # a staging folder (packaging, a look at the kit) is written, with the reason it
        # would not start as installed; installing it into / refuses
        click.echo(f"warning: {exc}", err=True)
        protect_home = "yes"
    if protect_home != "yes":
        click.echo(f"note: {exec_path} lies under a home folder: ProtectHome={protect_home}")
    allow = tuple(service_kit.check_allow_ip(a) for a in allow_ip)
    files = service_kit.plan(exec_path, protect_home=protect_home, allow_ip=allow)
    if dry_run:
        for kit_file in files:
            note = " (kept if it exists)" if kit_file.config else ""
            click.echo(f"--- would write {prefix.rstrip('/')}/{kit_file.path}{note}")
            click.echo(kit_file.text)
    else:
        try:
            results = service_kit.install(files, prefix)
        except PermissionError as exc:
            raise click.ClickException(
                f"{exc}; run with sudo, or --prefix a folder you can write"
            ) from exc
        for path, what in results:
            click.echo(f"{what:9} {path}")
        if warmup if warmup is not None else Path(prefix).resolve() == Path("/"):
            report = service_kit.warm_cache(exec_path, prefix)
            click.echo(
                f"warmed    {Path(prefix) / service_kit.CACHE_PATH}: {report['kernels']} kernels "
                f"in {report['seconds']:.1f} s ({len(report['compiled'])} compiled)"
            )
    click.echo("\nthen, as root:" if not dry_run else "--- then, as root:")
    for step in service_kit.next_steps(prefix):
        click.echo(f"  {step}")
    return 0


@command.command("show")
@click.argument("what", type=click.Choice(["unit", "udev", "sysusers", "env"]))
def show(what: str) -> int:
    """Print one kit file (e.g. to review it, or pipe it where you want)."""
    render = {
        "unit": lambda: service_kit.render_unit(service_kit.default_exec()),
        "udev": service_kit.render_udev,
        "sysusers": service_kit.render_sysusers,
        "env": service_kit.render_env,
    }[what]
    click.echo(render(), nl=False)
    return 0
