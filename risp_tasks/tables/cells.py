"""One function per table: a cell (environment × method × repeat) → a JSON-able result.

A result is ``{"value": float, ...}`` (lower is better) or ``{"na": reason}`` — never a made-up number.

* estimation — per-image L1 state error (the paper's metric: (1/S) Σ_i |ŝ_i − s_i|, angles wrapped to
  (−π, π]; risp_train.evaluate) on the ``n_test`` target-domain images of repeat k (random looks), averaged
  over the images.  Optimising methods start every image at the ``average`` state and run ``iterations``
  RMSProp steps (lr ``TableConfig.lr``, momentum 0.5) through the tasks' shared loop.
* sysid — mean absolute error of the identified parameter(s) (quadrotor mass [kg], cube log10 k_n, hand
  joint stiffnesses (mean of 5), rod log10 E) on repeat k's target-domain reference video (risp_tasks.tasks).
* imitation — RMSE between the reference and the reproduced states (risp_tasks.tasks ``state_rmse_final``).
* control — per-state L1 error between the reached and the pictured state (:func:`control`).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
import torch

from risp_data.atomic import temp_prefix

from .artifacts import Artifacts
from .config import repeat_seed
from ..tasks.features import feature_extractor
from .methods import get_method

# ------------------------------------------------------------------------------------------ estimation


def load_images(shards_dir: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(images (N, H, W, 3) float32, states (N, S) float64) of a shard folder, in shard order."""
    from risp_train.data import iter_batches, open_shards

    batches = list(iter_batches(open_shards(shards_dir), batch_size=64))
    return torch.cat([b["image"] for b in batches]), torch.cat([b["state"] for b in batches])


def average_state(env, shards_dir: str) -> torch.Tensor:
    """target_to_state of the mean network target over the training set (circular mean for sin/cos pairs)."""
    _, states = load_images(shards_dir)
    return env.target_to_state(env.state_to_target(states).mean(0, keepdim=True))[0]


def prediction_errors(env, pred: torch.Tensor, true: torch.Tensor) -> dict:
    """A cell's state errors on its test images: the paper's per-image L1 (angles wrapped; mean, std over images)
    and the per-group errors in their units (issue 8: metres, degrees geodesic, radians)."""
    from risp_train.evaluate import per_image_error, state_differences, summarize_groups

    diff = state_differences(pred.numpy(), true.numpy(), env.state_names)
    e = per_image_error(diff, "l1")
    return {"value": float(e.mean()), "std_images": float(e.std()), "n": len(pred), "metric": "l1",
            "per_dim_mae": np.abs(diff).mean(0).tolist(), "state_names": list(env.state_names),
            "groups": summarize_groups(env.name, pred.numpy(), true.numpy())}


def optimise_states(cfg, env, images: torch.Tensor, init: torch.Tensor, loss_name: str,
                    render_seed: int = 0) -> tuple[torch.Tensor, dict]:
    """Per-image analysis by synthesis: s ← argmin ‖R(s) − I‖² (pixelwise) or ‖F(R(s)) − F(I)‖² (perceptual),
    R = risp_data.diff_render in the train domain's nominal look, through the tasks' one loop, every render with
    sampler seed ``render_seed`` (the repeat's seed: repeats see independent render noise).  Returns the states
    and the loop's history (its ``stopped`` where a NaN/inf loss ended the descent)."""
    from risp_data.diff_render import StateRenderer
    from risp_tasks.tasks.loop import Problem, Timer, make_loss, optimize

    renderer = StateRenderer(env.name, resolution=cfg.resolution, spp=cfg.spp)
    states = init.detach().clone().to(torch.float32).requires_grad_(True)
    frames = list(range(len(images)))
    features = feature_extractor(cfg.perceptual_weights) if loss_name == "perceptual" else None
    loss = make_loss(loss_name, env, frames, None, None, images, renderer=renderer, features=features,
                     render_seed=render_seed)
    problem = Problem(variables={"states": states}, states=lambda: states, estimates=dict)
    history = optimize(problem, loss, optimizer="rmsprop", lr=cfg.lr, momentum=0.5, iterations=cfg.iterations,
                       timer=Timer(), progress=False)
    return states.detach().to(torch.float64), history


def estimation(cfg, art: Artifacts, env_name: str, method: str, repeat: int) -> dict:
    from risp_data.envs import get_environment

    env, m = get_environment(env_name), get_method(method)
    if m.loss == "state":
        return {"na": "in estimation `ours-state` is `ours`: N(I) itself, no simulator to fit"}
    images, true = load_images(art.test_shards(env_name, repeat))
    n = len(images)
    info: dict = {}
    if m.name == "oracle":
        pred = true
    elif m.name == "random":
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, repeat, 0x7AB1E]))
        pred = torch.from_numpy(np.asarray(env.sample_states(rng, n), np.float64))
    elif m.network is not None:
        from risp_train.predictor import load

        path = art.network(env_name, m.network)
        with torch.no_grad():
            pred = load(path)(images).to(torch.float64)
        info["model"] = path
    else:
        avg = average_state(env, art.train_shards(env_name))
        if m.name == "average":
            pred = avg.expand(n, -1)
        else:
            pred, history = optimise_states(cfg, env, images, avg.expand(n, -1), m.loss,
                                            render_seed=repeat_seed(cfg.seed, repeat))
            if "stopped" in history:
                info["stopped"] = history["stopped"]
            if m.name == "perceptual":
                info["extractor"] = feature_extractor(cfg.perceptual_weights).name
    return {**prediction_errors(env, pred, true), **info}


# ------------------------------------------------------------------------------------------ tasks


def _cell_folder(art: Artifacts):
    """A task cell's scratch folder under the table's root, named for its process (``.tmp-<pid>@<host>-cell-*``):
    removed when the cell ends, and by the next run (risp_data.atomic.remove_temporaries) when a kill left it."""
    return tempfile.TemporaryDirectory(prefix=temp_prefix() + "cell-", dir=art.root)


def _task_run(cfg, art: Artifacts, task: str, env_name: str, method: str, repeat: int, video: str | None = None,
              truth: str | None = None, start: str = "random", **task_kw) -> dict:
    """One risp_tasks.tasks run of ``method`` on repeat k's reference video; the result dict."""
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.run import run_task

    m = get_method(method)
    ref = art.video(env_name, repeat)
    # every method needs a network: the tasks read the initial state from N(first two frames); the
    # non-network methods use the `ours` network for that only
    model = art.network(env_name, m.network or "reg")
    loss = {None: "state", "render": "render", "state": "state", "pixelwise": "pixelwise",
            "perceptual": "perceptual", "oracle": "oracle"}[m.loss]
    # optimisers start at the seeded random guess (``start="random"``) or, for control, at the neutral actions
    init = "default" if m.name == "average" or (start == "neutral" and m.loss is not None) else "random"
    iterations = 0 if m.loss is None else cfg.iterations
    # the residual norm of the network-space losses: the table's (l2 by default, as the tables were made; sysid's
    # own default is l1 since 2026-11-28); the image losses (pixelwise, perceptual) are always squared
    from risp_tasks.tasks.config import NETWORK_LOSSES

    residual = cfg.residual if loss in NETWORK_LOSSES else "l2"
    with _cell_folder(art) as tmp:
        tcfg = TaskConfig(task=task, video=video or ref["video"], out=os.path.join(tmp, "result"), model=model,
                          loss=loss, init=init, iterations=iterations, seed=repeat_seed(cfg.seed, repeat),
                          actions=ref["actions"] if task == "sysid" else None, truth=truth or ref["truth"],
                          perceptual_weights=cfg.perceptual_weights if m.loss == "perceptual" else None,
                          spp=cfg.spp, residual=residual, plots=False, progress=False, render_threads=1, **task_kw)
        return run_task(tcfg, echo=lambda *_: None)


def _extras(result: dict) -> dict:
    """What a cell file keeps beside its value: F's name for a perceptual run (report.py names the extractor a table
    used), and where a descent stopped at a non-finite loss (risp_tasks.tasks.loop.optimize)."""
    name = result.get("info", {}).get("perceptual_extractor")
    return {**({"extractor": name} if name else {}), **({"stopped": result["stopped"]} if "stopped" in result else {})}


def sysid(cfg, art: Artifacts, env_name: str, method: str, repeat: int) -> dict:
    result = _task_run(cfg, art, "sysid", env_name, method, repeat)
    errors = result["errors"]["parameter_error_final"]
    return {"value": float(np.mean(list(errors.values()))), "errors": errors, "metric": "abs parameter error",
            "estimates": result["estimates"]["parameters"], "final_loss": result["final_loss"], **_extras(result)}


def imitation(cfg, art: Artifacts, env_name: str, method: str, repeat: int) -> dict:
    if env_name == "cube":
        return {"na": "the cube has no actions"}
    # the simulator's nominal parameters and one command row per frame, as the table was made and as every method
    # can be run (imitate's defaults identify the hand's and the rod's parameters with the commands, and choose the
    # hand's knots by N's readings, which the image baselines have not: docs/tasks.md §Unknown physical parameters,
    # §Knots chosen by cross-validation)
    result = _task_run(cfg, art, "imitate", env_name, method, repeat, fit_params=False, action_knots=0)
    return {"value": float(result["errors"]["state_rmse_final"]), "metric": "state RMSE",
            "initial": result["errors"].get("state_rmse_initial"), "final_loss": result["final_loss"],
            **_extras(result)}


def control(cfg, art: Artifacts, env_name: str, method: str, repeat: int) -> dict:
    """Adapter over ``risp-task control``: from the simulator state of repeat k's reference video at frame 0,
    reach the state pictured in its last frame (horizon = frames − 1) with the nominal simulator; the value is
    the per-state L1 error (angles wrapped) between the reached and the pictured state.  The optimising methods
    start from ``cfg.control_start``: the neutral actions (the `average` row) by default, so that a row below
    `average` is what its loss added; the `random` row stays the seeded random actions."""
    import json

    from PIL import Image

    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import frame_states, initial_sim_state, steps_per_frame, to_sim_actions
    from risp_tasks.video import read_video, to_uint8
    from risp_train.evaluate import state_differences

    if env_name == "cube":
        return {"na": "the cube has no actions"}
    ref = art.video(env_name, repeat)
    with open(ref["truth"]) as f:
        truth = json.load(f)
    horizon = cfg.frames - 1
    goal = np.asarray(truth["env_states"][horizon], np.float64)
    sim = get_simulator(env_name)
    if truth.get("sim_states") is not None:
        s0 = torch.tensor(truth["sim_states"][0], dtype=torch.float64)[None]
    else:  # large states (the rod) are not stored: its reference videos start at rest, as initial_sim_state does
        s0 = initial_sim_state(sim, torch.tensor(truth["env_states"][0], dtype=torch.float64), None, truth["fps"])
    with _cell_folder(art) as tmp:
        goal_png, init_json, goal_json = (os.path.join(tmp, n) for n in ("goal.png", "initial.json", "goal.json"))
        frame = read_video(ref["video"], resolution=cfg.resolution).frames[horizon]
        Image.fromarray(to_uint8(frame)).save(goal_png)
        with open(init_json, "w") as f:
            json.dump({"state": s0[0].tolist()}, f)
        with open(goal_json, "w") as f:  # the oracle loss compares the loss frame (the last) with this state
            json.dump({"env_states": [goal.tolist()]}, f)
        result = _task_run(cfg, art, "control", env_name, method, repeat, video=goal_png, truth=goal_json,
                           start=cfg.control_start, initial_state=init_json, horizon=horizon, fps=truth["fps"])
    params = sim.default_params()
    actions = to_sim_actions(sim, params, torch.tensor(result["estimates"]["actions"], dtype=torch.float64))
    with torch.no_grad():
        reached = frame_states(sim, params, s0, actions, horizon + 1, steps_per_frame(sim, truth["fps"]))[-1]
    diff = state_differences(reached.numpy()[None], goal[None], sim_env_names(env_name))
    return {"value": float(np.abs(diff).mean()), "metric": "l1", "reached": reached.tolist(), "goal": goal.tolist(),
            "final_loss": result["final_loss"], **_extras(result)}


def sim_env_names(env_name: str) -> tuple[str, ...]:
    from risp_data.envs import get_environment

    return get_environment(env_name).state_names


def regularized_epoch_seconds(history: list[dict], run_config: dict) -> list[float]:
    """Wall seconds of each epoch trained with the regularizer on: epoch e counts when its first step is at or after
    the start of γ(t), start_fraction · total steps (risp_train.regularizers.gamma_at).  Before it every regularizer
    trains as `none`, so a median over all epochs of a late-start schedule (the quadrotor's and the cube's start at
    half the run) would average the two costs.  A `none` run is timed over the same window (its config records the
    environment's start too).  Epochs of a resumed run whose clock restarted (negative differences) are dropped."""
    steps = list(run_config["steps_per_epoch"])
    start = float(run_config.get("gamma_start") or 0.0) * sum(steps)
    first_step = np.concatenate([[0], np.cumsum(steps)[:-1]])
    ends = {h["epoch"]: h["seconds"] for h in history if h.get("epoch", -1) >= 0}
    out, previous = [], 0.0
    for e in range(len(steps)):
        if e not in ends:
            break
        seconds, previous = ends[e] - previous, ends[e]
        if first_step[e] >= start and seconds > 0:
            out.append(float(seconds))
    return out


def regularizers(cfg, art: Artifacts, env_name: str, reg: str, repeat: int) -> dict:
    """The regularizer comparison (the paper's future work): a network trained with ``reg`` on the same training
    set with the same budget (epochs, batch, γ preset) and training seed ``repeat_seed(seed, repeat)``; its estimation error
    on repeat k's target-domain images and its median wall time per epoch with the regularizer on."""
    import json

    from risp_data.envs import get_environment
    from risp_train.predictor import load

    env = get_environment(env_name)
    path = art.network(env_name, reg, seed=repeat_seed(cfg.seed, repeat))
    images, true = load_images(art.test_shards(env_name, repeat))
    with torch.no_grad():
        pred = load(path)(images).to(torch.float64)
    run = os.path.dirname(path)
    with open(os.path.join(run, "history.json")) as f, open(os.path.join(run, "config.json")) as g:
        per_epoch = regularized_epoch_seconds(json.load(f), json.load(g))
    return {**prediction_errors(env, pred, true),
            "seconds_per_epoch": float(np.median(per_epoch)) if per_epoch else None,
            "timed_epochs": len(per_epoch), "model": path}


def sampling(cfg, art: Artifacts, env_name: str, scheme: str, repeat: int) -> dict:
    from .sampling import sampling as cell

    return cell(cfg, art, env_name, scheme, repeat)


CELLS = {"estimation": estimation, "sysid": sysid, "imitation": imitation, "control": control,
         "regularizers": regularizers, "sampling": sampling}
