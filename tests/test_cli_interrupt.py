"""Ctrl-C inside native code reads as an interrupt (exit 130), not as a failure of the renderer.

A KeyboardInterrupt that arrives while Dr.Jit runs a loop comes back as ``RuntimeError: dr.while_loop():
encountered an exception``; one during Mitsuba's import as a SystemError that risp names "cannot set Mitsuba
variant".  Both used to print a traceback or a wrong cause with exit 1 (risp_data.cli_util.caused_by_interrupt).
"""

from __future__ import annotations

import click
import pytest

from risp_data.cli_util import RispGroup, caused_by_interrupt, run_cli
from risp_data.errors import RispError


def _drjit_loop_interrupted():
    """A real Dr.Jit loop whose body is interrupted (as SIGINT would, between two bytecodes of the body)."""
    from risp_data.mitsuba_setup import init_mitsuba

    init_mitsuba("llvm_ad_rgb")
    import drjit as dr
    from drjit.llvm import Int

    def body(i):
        raise KeyboardInterrupt

    dr.while_loop(state=(Int(0),), cond=lambda i: i < 3, body=body)


def _import_interrupted():
    """The shape of the Mitsuba-import case: a SystemError caused by the interrupt, re-raised as a RispError."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError("<built-in function __import__> returned a result with an exception set") from ki
    except Exception as e:  # noqa: BLE001 - as mitsuba_setup does
        raise RispError(f"cannot set Mitsuba variant 'llvm_ad_rgb': {e}") from None


def test_the_chain_is_searched():
    with pytest.raises(RuntimeError) as info:
        _drjit_loop_interrupted()
    assert "while_loop" in str(info.value)  # Dr.Jit's wrapping, as seen from the command line
    assert caused_by_interrupt(info.value)
    with pytest.raises(RispError) as info:
        _import_interrupted()
    assert caused_by_interrupt(info.value)
    assert not caused_by_interrupt(RuntimeError("a real failure"))
    try:
        raise ValueError("inner")
    except ValueError as inner:
        outer = RuntimeError("outer")
        outer.__context__ = inner
    assert not caused_by_interrupt(outer)


@pytest.mark.parametrize("raiser", [_drjit_loop_interrupted, _import_interrupted], ids=["drjit-loop", "mitsuba-import"])
def test_command_interrupted_in_native_code_exits_130(raiser, capsys):
    @click.group(cls=RispGroup)
    def group():
        pass

    @group.command()
    def work():
        raiser()

    with pytest.raises(SystemExit) as info:
        run_cli(group, ["work"])
    assert info.value.code == 130
    err = capsys.readouterr().err
    assert "Error: interrupted" in err
    assert "Mitsuba" not in err and "Traceback" not in err


def test_a_real_error_still_exits_1(capsys):
    @click.group(cls=RispGroup)
    def group():
        pass

    @group.command()
    def work():
        raise RispError("shards/x: not a data set")

    with pytest.raises(SystemExit) as info:
        run_cli(group, ["work"])
    assert info.value.code == 1
    assert capsys.readouterr().err.strip() == "Error: shards/x: not a data set"


def test_an_unknown_name_is_one_line_and_status_1_a_missing_option_a_usage_error(capsys):
    """--env nosuch is bad input like any other (docs/cli.md: one line, status 1), where click alone would print
    its usage lines and exit 2; a missing required option stays click's usage error (status 2)."""
    @click.group(cls=RispGroup)
    def group():
        pass

    @group.command()
    @click.option("--env", type=click.Choice(["cube", "rod"]), required=True)
    @click.option("--n", type=int, default=1)
    def work(env, n):
        pass

    for args, words in ((["--env", "nosuch"], "'nosuch' is not one of 'cube', 'rod'"),
                        (["--env", "rod", "--n", "x"], "'x' is not a valid integer")):
        with pytest.raises(SystemExit) as info:
            run_cli(group, ["work", *args])
        err = capsys.readouterr().err.strip()
        assert info.value.code == 1 and err.startswith("Error: ") and words in err and "\n" not in err, err
    with pytest.raises(SystemExit) as info:
        run_cli(group, ["work"])
    assert info.value.code == 2 and "Missing option '--env'" in capsys.readouterr().err


@pytest.mark.parametrize("module", ["cli", "risp_data.cli", "risp_train.cli", "risp_tasks.cli"])
def test_every_command_group_prints_its_version(module):
    import importlib
    from importlib.metadata import version

    from click.testing import CliRunner

    res = CliRunner().invoke(importlib.import_module(module).cli, ["--version"])
    assert res.exit_code == 0 and res.output.strip().endswith(f"(risp) {version('risp')}"), res.output
