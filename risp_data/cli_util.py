"""Helpers shared by the three command-line tools: one error line, non-zero exit."""

from __future__ import annotations

import sys

import click

from .errors import RispError


def run_cli(group: click.Group, argv: list[str] | None = None) -> None:
    """Run a click group; a :class:`RispError` becomes ``error: <message>`` on stderr and exit status 1."""
    try:
        group.main(args=argv, standalone_mode=False)
    except RispError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(1)
    except click.exceptions.Abort:
        click.echo("error: aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except KeyboardInterrupt:
        click.echo("error: interrupted", err=True)
        sys.exit(130)


class RispGroup(click.Group):
    """A click group whose sub-commands turn :class:`RispError` into one error line (also under CliRunner)."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except RispError as e:
            raise click.ClickException(str(e)) from None
