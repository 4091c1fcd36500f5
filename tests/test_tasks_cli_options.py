"""risp-task's shared options: each task's --help lists the ones it uses, and any other task refuses them with
one line naming whose option it is (docs/cli-task.md) — not click's "No such option" usage error."""

import pytest
from click.testing import CliRunner

from risp_tasks.cli import ONLY_FOR, cli

TASKS = ("estimate", "sysid", "imitate", "control")
# a value for each option that takes one (the flags are given as they are)
VALUES = {"--grow-horizon": ["3"], "--action-knots": ["4"], "--params": ['{"mass": 3.0}'], "--actions": ["a.csv"],
          "--every": ["2"], "--source-fps": ["10"], "--fit-initial-state": [], "--fit-params": [],
          "--initial-state": ["s.json"], "--horizon": ["5"]}
# the negative forms of the boolean pairs are refused too
NEGATIVE = {"--fit-initial-state": "--fixed-initial-state", "--fit-params": "--no-fit-params"}


def test_every_restricted_option_has_a_test_value():
    assert set(ONLY_FOR) == set(VALUES)


@pytest.mark.parametrize("task", TASKS)
def test_help_lists_the_options_a_task_uses(task):
    res = CliRunner().invoke(cli, [task, "--help"], terminal_width=200)
    assert res.exit_code == 0, res.output
    for option, users in ONLY_FOR.items():
        assert (option in res.output) == (task in users), (task, option)


@pytest.mark.parametrize("task, residual, iterations", [("estimate", "l2", "0: the network's readings as they are"),
                                                         ("sysid", "l1", "100"), ("imitate", "l2", "100"),
                                                         ("control", "l2", "100")])
def test_help_gives_each_tasks_own_defaults(task, residual, iterations):
    """A task's --help states its own defaults, not every task's ('l1 in sysid, l2 otherwise'), and drops the
    'sysid, imitate:' that names whose option it is where it is the task's own."""
    from risp_tasks.cli import TASKS_PREFIX

    res = CliRunner().invoke(cli, [task, "--help"], terminal_width=400)
    text = " ".join(res.output.split())
    assert f"differences [default: {residual}]" in text and f"optimisation iterations [default: {iterations}]" in text
    assert "otherwise]" not in text and "estimate: 0]" not in text
    command = cli.commands[task]
    for param in command.params:
        said = TASKS_PREFIX.match(param.help or "")
        assert not (said and task in said.group(1).split(", ")), (task, param.name, param.help)


@pytest.mark.parametrize("task, option", [(t, o) for o, users in ONLY_FOR.items() for t in TASKS if t not in users])
def test_another_task_s_option_is_refused_in_one_line(task, option, tmp_path):
    target = str(tmp_path / ("goal.png" if task == "control" else "video.mp4"))
    for given in filter(None, (option, NEGATIVE.get(option))):
        args = [given, *VALUES[option]]
        res = CliRunner().invoke(cli, [task, target, *args, "--out", str(tmp_path / "res"), "--quiet"])
        lines = res.output.strip().splitlines()
        assert res.exit_code == 1, (task, given, res.output)
        assert len(lines) == 1 and lines[0].startswith("Error:"), res.output
        assert "No such option" not in res.output
        assert option in lines[0], lines[0]  # the line names the option (and whose it is)
        assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("task, args", [("sysid", ["--fit-params"]), ("estimate", ["--no-fit-params"]),
                                        ("control", ["--fit-initial-state"]), ("estimate", ["--fixed-initial-state"])])
def test_the_boolean_options_of_sysid_and_imitate_are_refused_by_the_others(task, args, tmp_path):
    """Before: click's usage error ("No such option", exit 2) instead of the line saying whose option it is."""
    res = CliRunner().invoke(cli, [task, str(tmp_path / "v.mp4"), *args, "--quiet"])
    assert res.exit_code == 1 and "is for" in res.output and "No such option" not in res.output, res.output


def test_the_help_says_what_the_code_does(tmp_path):
    """--limit keeps the first N files in the order given (not sorted by name: measured.expand_paths); make-video's
    --domain says what each look is; control's --model has no video tag to follow; the group names every command."""
    from risp_tasks.measured import expand_paths

    for name in ("b.csv", "a.csv"):
        (tmp_path / name).write_text("t\n0\n")
    assert [p.name for p in expand_paths([str(tmp_path / "b.csv"), str(tmp_path / "a.csv")])] == ["b.csv", "a.csv"]

    def helptext(*args):
        res = CliRunner().invoke(cli, [*args, "--help"], terminal_width=400)
        assert res.exit_code == 0, res.output
        return " ".join(res.output.split())

    assert "the first N files: in the order given, a folder's CSVs in name order" in helptext("diagnose")
    assert "train: a look drawn as the networks' training images are" in helptext("make-video")
    assert "make-video tag" not in helptext("control") and "make-video tag" in helptext("imitate")
    group = helptext().split("Commands:")[0]  # the group's own text (the command list names every command anyway)
    assert "make-video" in group and "table" in group
