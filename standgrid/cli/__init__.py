"""The ``standgrid`` command: a thin click group over the Python API.

Subcommands live one per module and are imported only when run, so ``--help`` is instant.
Library errors become clean one-line messages here, in one place.
"""

from __future__ import annotations

import importlib
import logging

import click

from standgrid.errors import OptionError, StandgridError

#: command name -> "module:attribute" of its click command.
COMMANDS: dict[str, str] = {
    "info": "standgrid.cli.info:info",
    "missions": "standgrid.cli.missions:missions",
    "retrieve": "standgrid.cli.retrieve:retrieve",
    "payloads": "standgrid.cli.payloads:payloads",
    "simulate": "standgrid.cli.simulate:simulate",
    "georef": "standgrid.cli.georef:georef",
    "tile": "standgrid.cli.tile:tile",
    "align": "standgrid.cli.align:align",
    "enrich": "standgrid.cli.enrich:enrich",
    "compare": "standgrid.cli.compare:compare",
    "run": "standgrid.cli.run:run",
    "status": "standgrid.cli.status:status",
    "export": "standgrid.cli.export:export",
    "bag": "standgrid.cli.bag:bag",
    "serve": "standgrid.cli.serve:serve",
}


class LazyGroup(click.Group):
    """A group whose subcommands are imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(name for name in COMMANDS if self._load(name) is not None)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        return self._load(cmd_name)

    @staticmethod
    def _load(name: str) -> click.Command | None:
        target = COMMANDS.get(name)
        if target is None:
            return None
        module_name, attr = target.split(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:  # subcommand not built yet
                return None
            raise
        command: click.Command = getattr(module, attr)
        return command

    def invoke(self, ctx: click.Context) -> object:
        _say_lock_waits()
        try:
            return super().invoke(ctx)
        except StandgridError as exc:
            from standgrid.cli.options import say_flags

            # the library names options by their fields: here, and only here, as flags
            text = f"{type(exc).__name__}: {say_flags(str(exc))}"
            if isinstance(exc, OptionError):  # a value out of its range: a usage error
                raise click.UsageError(text) from exc
            raise click.ClickException(text) from exc


class _StderrLines(logging.Handler):
    """Log records as plain lines on stderr (click's stream: CliRunner captures it)."""

    def emit(self, record: logging.LogRecord) -> None:
        click.echo(self.format(record), err=True)


def _say_lock_waits() -> None:
    """Print "waiting for readers/another process" lines (the catalog's lock waits)."""
    logger = logging.getLogger("standgrid.catalog")
    logger.disabled = False  # a library's dictConfig (pyfvs) may have disabled it
    if not any(isinstance(h, _StderrLines) for h in logger.handlers):
        logger.addHandler(_StderrLines())
        logger.setLevel(logging.INFO)
        logger.propagate = False


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="standgrid")
def cli() -> None:
    """Forest-mapping robot missions in; a georeferenced stand-grid map out.

    \b
    Example:
      standgrid info data/missions/2024-05-14-wytham-anymal-coyote
    """


def main() -> None:
    cli(prog_name="standgrid")


if __name__ == "__main__":  # pragma: no cover
    main()
