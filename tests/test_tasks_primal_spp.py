"""The compared frames' samples per pixel (--primal-spp; docs/tasks.md §Primal spp): --spp unless given, recorded
in result.json; the checkpoint records its training images' spp."""

import json

import pytest
from click.testing import CliRunner

from tasks_helpers import shared_model, shared_video


def test_the_checkpoint_records_the_training_images_spp(tmp_path_factory):
    import risp_train
    from risp_train.checkpoint import load_checkpoint

    model = shared_model(tmp_path_factory, "quadrotor")  # rendered with --spp 2 (tasks_helpers.tiny_model)
    assert load_checkpoint(model)["spp"] == 2
    assert risp_train.load(model).spp == 2


@pytest.mark.parametrize("loss", ["render", "pixelwise", "perceptual", "state"])
def test_primal_spp_is_spp_unless_given(loss):
    from risp_tasks.tasks.config import TaskConfig

    assert TaskConfig(task="sysid", video="v.mp4", loss=loss, spp=3).primal_spp == 3
    assert TaskConfig(task="sysid", video="v.mp4", loss=loss, spp=3, primal_spp=16).primal_spp == 16


def test_the_cli_passes_primal_spp_to_the_task_and_records_it(tmp_path_factory, tmp_path):
    from risp_tasks.cli import cli

    model, video = shared_model(tmp_path_factory, "quadrotor"), shared_video(tmp_path_factory, "quadrotor")
    res = CliRunner().invoke(cli, ["estimate", video, "--model", model, "--primal-spp", "3", "--out",
                                   str(tmp_path / "o"), "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    config = json.load(open(tmp_path / "o" / "result.json"))["config"]
    assert config["primal_spp"] == 3 and config["spp"] == 4


def test_a_bad_primal_spp_is_one_line():
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match=r"--primal-spp must be >= 1, got 0"):
        TaskConfig(task="sysid", video="v.mp4", loss="render", primal_spp=0)
