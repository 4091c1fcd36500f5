"""The ``risp`` command group: ``risp data …``, ``risp train …``, ``risp task …`` and ``risp demo``.

Each sub-group is the same click group as the stand-alone ``risp-data``, ``risp-train`` and ``risp-task``
commands; ``risp demo`` runs the small built-in end-to-end job described in the README.
"""

from __future__ import annotations

import click

from risp_data.cli_util import RispGroup, run_cli


class _LazyGroup(RispGroup):
    """Import sub-command groups only when they are used, so ``risp --help`` stays fast."""

    _targets = {
        "data": ("risp_data.cli", "cli"),
        "train": ("risp_train.cli", "cli"),
        "task": ("risp_tasks.cli", "cli"),
        "demo": ("risp_tasks.demo", "demo"),
    }

    def list_commands(self, ctx):
        return sorted(self._targets)

    def get_command(self, ctx, name):
        if name not in self._targets:
            return None
        import importlib

        module, attr = self._targets[name]
        return getattr(importlib.import_module(module), attr)


@click.group(cls=_LazyGroup)
@click.version_option(package_name="risp", message="%(prog)s (risp) %(version)s")
def cli():
    """risp: recover states, parameters and actions from video with RISP."""


def main():
    run_cli(cli)  # user errors of every sub-command (``risp demo`` included): one ``Error:`` line


if __name__ == "__main__":
    main()
