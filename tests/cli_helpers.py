"""Test helper for the console scripts' error path (risp_data.cli_util.run_cli), which CliRunner does not take:
under CliRunner click prints its usage lines and exits 2 for a bad option value, the installed command one line
and status 1."""

from __future__ import annotations

import pytest


def console_error_line(group, argv: list[str], capsys) -> str:
    """Run ``group`` as its console script would with ``argv``; assert status 1 and exactly one ``Error:`` line of
    output, and return that line."""
    from risp_data.cli_util import run_cli

    with pytest.raises(SystemExit) as info:
        run_cli(group, argv)
    captured = capsys.readouterr()
    lines = [ln for ln in (captured.out + captured.err).splitlines() if ln.strip()]
    assert info.value.code == 1 and len(lines) == 1 and lines[0].startswith("Error: "), lines
    return lines[0]
