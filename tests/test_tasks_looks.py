"""The render loss read in several looks (--looks K; docs/tasks.md §Several looks): N's readings of each simulated
frame averaged over K random train-domain looks, each frame's gradient taken in the look it was rendered in."""

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tasks_helpers import shared_model, shared_video

pytestmark = pytest.mark.timeout(600)


def _looks(env_name, k, seed=4):
    from risp_data.psi import sample_rendering

    rng = np.random.default_rng(seed)
    return [sample_rendering(env_name, "train", rng) for _ in range(k)]


def test_each_frames_backward_runs_in_the_look_it_was_rendered_in():
    """Render the same states in look A, then in look B, and differentiate a weighted sum of both images: the
    state gradient is the sum of the gradients taken in A alone and in B alone.  Had the backward passes run in the
    scene as the last forward pass left it (look B), it would be twice B's — which differs from A + B here, because
    the two looks' gradients differ."""
    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment

    env = get_environment("rod")
    renderer = StateRenderer("rod", resolution=16, spp=2)
    a, b = _looks("rod", 2)
    states0 = torch.from_numpy(np.asarray(env.sample_states(np.random.default_rng(1), 2), np.float32))
    weight = torch.from_numpy(np.random.default_rng(2).standard_normal((2, 16, 16, 3)).astype(np.float32))

    def gradient(looks):
        states = states0.clone().requires_grad_(True)
        total = 0.0
        for look in looks:
            renderer.set_look(look)
            total = total + (renderer(states, seed=0) * weight).sum()
        total.backward()
        return states.grad.double()

    g_a, g_b, g_ab = gradient([a]), gradient([b]), gradient([a, b])
    assert torch.linalg.norm(g_a - g_b) > 0.05 * torch.linalg.norm(g_a)  # the looks' gradients differ
    assert torch.allclose(g_ab, g_a + g_b, rtol=1e-4, atol=1e-6 * float(torch.linalg.norm(g_a + g_b)))


def test_the_render_loss_averages_the_readings_over_the_looks(tmp_path_factory):
    """make_loss("render", looks=[A, B]) = ‖(N(R_A(s)) + N(R_B(s)))/2 − goal‖₁ per frame, as computed by hand; one
    look alone (or none) reads the renderer's own look; the other losses refuse looks."""
    import risp_train
    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_data.errors import RispError
    from risp_tasks.tasks.loop import make_loss

    predictor = risp_train.load(shared_model(tmp_path_factory, "rod"))
    env = get_environment("rod")
    renderer = StateRenderer("rod", resolution=predictor.resolution, spp=1)
    nominal = renderer.config
    a, b = _looks("rod", 2, seed=7)
    states = torch.from_numpy(np.asarray(env.sample_states(np.random.default_rng(3), 2), np.float32))
    goal = torch.zeros(2, len(env.target_names), dtype=torch.float64)

    def read(look):
        renderer.set_look(look)
        return predictor.predict(renderer(states, seed=5))[1].double()

    with torch.no_grad():
        by_hand = float(((read(a) + read(b)) / 2 - goal).abs().sum(-1).mean())
        nominal_by_hand = float((read(nominal) - goal).abs().sum(-1).mean())
        renderer.set_look(nominal)
        two = float(make_loss("render", env, [0, 1], goal, None, None, predictor=predictor, renderer=renderer,
                              residual="l1", render_seed=5, looks=[a, b])(states))
        renderer.set_look(nominal)
        one = float(make_loss("render", env, [0, 1], goal, None, None, predictor=predictor, renderer=renderer,
                              residual="l1", render_seed=5)(states))
    assert two == pytest.approx(by_hand, rel=1e-5)
    assert one == pytest.approx(nominal_by_hand, rel=1e-5)
    assert two != pytest.approx(one, rel=1e-3)
    with pytest.raises(RispError, match="several looks are for the render loss"):
        make_loss("pixelwise", env, [0, 1], None, None, None, renderer=renderer, looks=[a, b])
    with pytest.raises(RispError, match="looks is empty"):
        make_loss("render", env, [0, 1], goal, None, None, predictor=predictor, renderer=renderer, looks=[])


def test_looks_are_drawn_from_the_seed_and_recorded(tmp_path_factory, tmp_path):
    """sysid --loss render --looks 2: the run's result.json records two train-domain looks, the same for the same
    --seed and others for another; the run writes its plots."""
    from risp_tasks.cli import cli
    from risp_tasks.tasks.run import render_looks

    model, video = shared_model(tmp_path_factory, "rod"), shared_video(tmp_path_factory, "rod")
    stem = video.rsplit(".", 1)[0]
    res = CliRunner().invoke(cli, ["sysid", video, "--model", model, "--actions", stem + ".actions.csv",
                                   "--loss", "render", "--looks", "2", "--iterations", "1", "--spp", "1",
                                   "--seed", "3", "--out", str(tmp_path / "o"), "--quiet"])
    assert res.exit_code == 0, res.output
    r = json.load(open(tmp_path / "o" / "result.json"))
    assert r["config"]["looks"] == 2
    looks = r["info"]["looks"]
    assert len(looks) == 2 and all(look["domain"] == "train" for look in looks)
    again = render_looks("rod", 2, 3)
    assert [look["psi"] for look in looks] == [list(map(float, c.psi)) for c in again]
    assert looks[0]["psi"] != looks[1]["psi"]
    assert render_looks("rod", 2, 4)[0].psi.tolist() != looks[0]["psi"]
    assert render_looks("rod", 1, 3) is None
    assert (tmp_path / "o" / "frames.png").exists()


@pytest.mark.parametrize("loss, said", [("state", "reads no rendered frame"), ("oracle", "reads no rendered frame"),
                                        ("pixelwise", "compares images"), ("perceptual", "compares images")])
def test_looks_other_than_one_need_the_render_loss(loss, said):
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match=f"--looks averages .*{said}"):
        TaskConfig(task="sysid", video="v.mp4", loss=loss, looks=2, truth="t.json")
    with pytest.raises(RispError, match=r"--looks must be >= 1, got 0"):
        TaskConfig(task="sysid", video="v.mp4", loss="render", looks=0)
    assert TaskConfig(task="sysid", video="v.mp4", loss=loss, truth="t.json").looks == 1


@pytest.mark.parametrize("args, said", [(["--loss", "state", "--looks", "2"], "--loss state reads no rendered frame"),
                                        (["--loss", "render", "--looks", "0"], "--looks must be >= 1, got 0")])
def test_a_bad_looks_on_the_command_line_is_one_line_and_writes_nothing(tmp_path, args, said):
    from risp_tasks.cli import cli

    out = tmp_path / "o"
    res = CliRunner().invoke(cli, ["sysid", str(tmp_path / "v.mp4"), *args, "--out", str(out)])
    assert res.exit_code != 0
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and said in lines[0], res.output
    assert not out.exists()
