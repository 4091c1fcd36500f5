"""Run one task: load → reference → problem → shared loop → result folder (docs/tasks.md)."""

from __future__ import annotations

import importlib
import os
import time

import numpy as np
import torch

from risp_data.errors import RispError
from risp_data.threads import set_drjit_threads, set_torch_threads
from risp_train.checkpoint import model_file

from . import TASKS
from .config import TaskConfig
from .context import Context
from .inputs import (load_model, look_note, model_env, models_newest_first, read_actions, read_camera, read_reference,
                     read_truth, render_environment)
from .loop import Timer, make_loss, optimize
from .reference import truth_path
from .results import ResultFolder, check_free, plot_loss, plot_scan, plot_trajectories, save_strip, versions
from .sysid import bound_warnings

STRIP_FRAMES = 6


def default_out(cfg: TaskConfig) -> str:
    stem = os.path.splitext(os.path.basename(os.path.normpath(cfg.video)))[0]
    return os.path.join("results", f"{cfg.task}-{stem}-seed{cfg.seed}")


def resolve_model(cfg: TaskConfig) -> tuple[str, str]:
    """(checkpoint path, the line saying which one is used)."""
    if cfg.model is not None:
        path = model_file(cfg.model)  # a run folder names its model.pt
        return path, f"model: {path}"
    wanted = cfg.env or (video_system(cfg.video) if cfg.task != "control" else None)
    found = models_newest_first(cfg.runs)
    newest = found[0]
    # the newest of the wanted system; with none of it, the newest of any (the caller then names the mismatch)
    path = next((p for p in found if model_env(p) == wanted), newest) if wanted else newest
    if os.path.getmtime(path) < os.path.getmtime(newest):  # a newer run of another system lies there: say why
        why = "--env" if cfg.env else "the video's system (make-video's tag)"
        return path, f"model: {path} (the most recent {wanted} model under {cfg.runs}/, for {why})"
    return path, f"model: {path} (the most recent under {cfg.runs}/)"


def video_system(path: str) -> str | None:
    """The system a make-video file (or PNG folder: its frames' Comment chunk) names in its tag; None for other
    footage."""
    from ..video import comment_tag, made_for

    return made_for(comment_tag(path))


def _reference(cfg: TaskConfig, resolution: int):
    """(frames (T, r, r, 3), keep, n_source, fps, sha256, ref) — a video, or for ``control`` one goal image.

    ``keep`` are the kept frames' indices on the simulation timeline of ``n_source`` frames at ``fps`` (one actions
    row each); ``ref`` (inputs.Reference; None for ``control``) has the kept frames' indices among the decoded ones,
    their count and rate: where a ground truth written at the video's own rate is read (with ``--fps`` the two
    timelines differ)."""
    if cfg.task == "control":
        from ..video import read_rgb8, resize, sha256_file, srgb_to_linear

        path = cfg.video
        if os.path.isdir(path):
            raise RispError(f"{path}: a folder, but control takes one target image (a PNG or JPEG file)")
        if not os.path.isfile(path):
            raise RispError(f"{path}: target image not found")
        try:
            img = read_rgb8(path).astype(np.float32) / 255.0
        except Exception as e:  # noqa: BLE001 - PIL raises several types
            raise RispError(f"{path}: cannot read the target image ({type(e).__name__})") from None
        frames = resize(srgb_to_linear(img)[None], resolution)
        return frames, [0], 1, float(cfg.fps if cfg.fps is not None else 10.0), sha256_file(path), None
    from ..video import sample_indices

    ref = read_reference(cfg.video, resolution, cfg.every, cfg.fps, cfg.source_fps)
    if cfg.fps is not None:  # the timeline is the resampled one (an actions file has one row per resampled frame)
        n_resampled = len(sample_indices(ref.n_source, ref.source_fps, cfg.fps, 1))
        return ref.video.frames, list(range(0, n_resampled, cfg.every)), n_resampled, float(cfg.fps), ref.sha256, ref
    return ref.video.frames, ref.indices, ref.n_source, ref.source_fps, ref.sha256, ref


def _check_action_range(path: str, sim, file_actions: np.ndarray) -> None:
    """Commands the simulator cannot apply: quadrotor thrusts [N] beyond its commands' clamp at ±COMMAND_LIMIT,
    rod centre forces [N] beyond FORCE_LIMIT.  The file is in other units (grams, RPM, mN) — its commands would
    have been clipped without a word.  (The hand's torques have no clamp in the model: nothing to check.)"""
    worst = float(np.abs(file_actions).max()) if file_actions.size else 0.0
    if sim.env == "rod":
        from ..sims.rod import FORCE_LIMIT

        if worst > FORCE_LIMIT:
            raise RispError(f"{path}: centre forces up to {worst:.4g} N, above the {FORCE_LIMIT:g} N the simulated rod "
                            f"takes: the column u0 is a force in newtons (docs/tasks.md §Actions CSV)")
        return
    if sim.env != "quadrotor":
        return
    from ..sims.quadrotor import COMMAND_LIMIT

    k_f = float(sim.default_params()[0, sim.param_index("k_f")])
    limit = COMMAND_LIMIT * k_f
    if worst > limit:
        raise RispError(f"{path}: rotor thrusts up to {worst:.4g} N, above the {limit:.4g} N the simulated rotors can "
                        f"give: the columns f0..f3 are thrusts in newtons per rotor (docs/tasks.md §Actions CSV)")


def _check_truth_timeline(cfg: TaskConfig, truth: dict, ref) -> None:
    """A truth file's frame count and rate must be the video's (a truth without ``video_sha256``, as make-video
    wrote before 2026-11-29, was compared row by row with another video's frames)."""
    frames, fps = truth.get("frames"), truth.get("fps")
    if isinstance(frames, int) and frames != ref.video.source_frames:
        raise RispError(f"{cfg.truth}: the ground truth of a {frames}-frame video, but {cfg.video} has "
                        f"{ref.video.source_frames} frames: give the truth written beside this video")
    if isinstance(fps, (int, float)) and ref.source_fps > 0 and abs(fps - ref.source_fps) > 0.01 * ref.source_fps:
        raise RispError(f"{cfg.truth}: the ground truth of a {fps:g} fps video, but {cfg.video} runs at "
                        f"{ref.source_fps:g} fps: give the truth written beside this video")


TASK_STREAM = 0x7A5C  # tags the tasks' random stream apart from make-video's (which is default_rng(seed))


def task_rng(seed: int) -> np.random.Generator:
    """The task's random draws (``--init random``): SeedSequence(seed, TASK_STREAM).  Until 2026-12-01 it was
    default_rng(seed), the stream make-video draws a video's hidden parameters from first, so ``sysid --init random
    --seed S`` on make-video's ``--seed S`` video started exactly at the true parameters."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), TASK_STREAM]))


LOOKS_STREAM = 0x100C  # the render loss's random looks (--looks K > 1), a stream apart from --init random's


def render_looks(env_name: str, count: int, seed: int) -> list | None:
    """The looks whose readings the render loss averages (``--looks``): None for 1 (the renderer's nominal look),
    else ``count`` random train-domain looks ψ_1…ψ_K drawn from SeedSequence(seed, LOOKS_STREAM) — fixed for the
    whole descent, so that its iterates are compared on the same looks."""
    if count <= 1:
        return None
    from risp_data.psi import sample_rendering

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), LOOKS_STREAM]))
    return [sample_rendering(env_name, "train", rng) for _ in range(count)]


PREDICT_BATCH = 256  # frames N reads at once: its activations for a whole long video at once did not fit in memory


def predict_frames(predictor, frames: torch.Tensor, batch: int | None = None, progress: bool = True
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """N's readings (states (T, S), targets (T, T')) of the frames (T, r, r, 3), ``batch`` (default PREDICT_BATCH)
    frames at a time; the same numbers as one call on all of them (eval mode: no frame sees another)."""
    from tqdm import tqdm

    batch = batch or PREDICT_BATCH
    states, targets = [], []
    with torch.no_grad():
        for start in tqdm(range(0, len(frames), batch), desc="reading the frames", unit="batch", leave=False,
                          disable=not progress):
            s, t = predictor.predict(frames[start:start + batch])
            states.append(s)
            targets.append(t)
    return torch.cat(states), torch.cat(targets)


def check_samples(cfg: TaskConfig, resolution: int) -> None:
    """Refuse, before any work, an ``--spp`` or ``--primal-spp`` Mitsuba cannot render: it counts the samples of one
    render launch in a uint32, and the tasks' renderer launches one frame at a time at the model's resolution in the
    train domain (no spp factor), i.e. spp × resolution² samples (a larger count failed deep inside Mitsuba)."""
    from risp_data.generate import MITSUBA_MAX_SAMPLES

    for option, spp in (("--spp", cfg.spp), ("--primal-spp", cfg.primal_spp)):
        samples = spp * resolution * resolution
        if samples >= MITSUBA_MAX_SAMPLES:
            raise RispError(f"{option} {spp} needs {samples:,} samples per rendered frame ({resolution}×{resolution} "
                            f"pixels, the model's), beyond Mitsuba's limit of 2^32 per render: lower {option}")


def _check_system_before_decoding(cfg: TaskConfig, env_name: str, chosen: str, made: str | None) -> None:
    """Before a frame is decoded: a make-video file whose tag (read from its header) names another system than the
    model's, and a system without actions asked to imitate, be controlled or given an actions file — one line each,
    ``chosen`` saying when the model was the newest under runs/ rather than given."""
    from ..sims import get_simulator

    if made is not None and made != env_name:  # a make-video file names its system; real footage names none
        raise RispError(f"{cfg.video}: a {made} video (make-video's tag in the file), but the model is a {env_name} "
                        f"model{chosen}")
    if get_simulator(env_name).action_dim == 0 and (cfg.actions is not None or cfg.task in ("imitate", "control")):
        what = f"{cfg.actions}: the {env_name} has no actions" if cfg.actions is not None else \
            f"the {env_name} has no actions to {cfg.task}; {cfg.task} works for: quadrotor, hand, rod"
        raise RispError(what + chosen)


def run_task(cfg: TaskConfig, echo=print) -> dict:
    """Run ``cfg.task``; returns the result dict (also written to ``<out>/result.json``)."""
    if cfg.task not in TASKS:
        raise RispError(f"unknown task {cfg.task!r}; choose one of: {', '.join(TASKS)}")
    out = cfg.out or default_out(cfg)
    check_free(out, cfg.overwrite)
    torch_threads = set_torch_threads(cfg.threads)  # one shared rule (risp_data.threads): 0 = the machine's CPUs
    started = time.perf_counter()
    model_path, model_line = resolve_model(cfg)
    echo(model_line)
    predictor = load_model(model_path, cfg.env)
    check_samples(cfg, predictor.resolution)
    note = look_note(predictor, model_path, cfg.loss, cfg.mesh)
    if note:
        echo(note)
    env_name = predictor.env_name
    from risp_data.envs import get_environment

    from ..sims import get_simulator
    from ..video import comment_tag, made_for, sha256_file
    from .simulate import timeline

    chosen = "" if cfg.model is not None else (f" (the most recent model under {cfg.runs}/, {model_path}, is a "
                                               f"{env_name} model: give --model of a run for the video's system)")
    _check_system_before_decoding(cfg, env_name, chosen, made_for(comment_tag(cfg.video)) if cfg.video else None)
    env = get_environment(env_name)
    drawn = render_environment(env_name, cfg.mesh)  # what the renderer draws (a bad mesh: one line, no work done)
    features = None
    if cfg.loss == "perceptual":  # F of the perceptual loss (a bad weights file: one line, no work done)
        from .features import feature_extractor

        features = feature_extractor(cfg.perceptual_weights)
    frames, keep, n_source, fps, video_sha, ref = _reference(cfg, predictor.resolution)
    # what the inputs' readers did that the user should know (e.g. --source-fps replacing the file's rate): with
    # the result's warnings at the end, not before a later error line
    input_notes = list(ref.video.notes) if ref is not None else []
    if cfg.task in ("sysid", "imitate") and len(frames) < 2:  # nothing moves in one frame: the start would be the result
        raise RispError(f"{cfg.video}: {cfg.task} needs at least 2 frames (the initial state and its velocity are read "
                        f"from the first two), got {len(frames)} after --every {cfg.every}"
                        f"{f' / --fps {cfg.fps:g}' if cfg.fps is not None else ''}")
    sim, k = timeline(env_name, fps) if cfg.task != "estimate" else (get_simulator(env_name), 1)
    frames_t = torch.from_numpy(frames)
    predicted, predicted_targets = predict_frames(predictor, frames_t, progress=cfg.progress)
    file_actions = None
    if cfg.actions is not None:
        file_actions = read_actions(cfg.actions, env_name, n_source, fps,
                                    f" at --fps {cfg.fps:g}" if cfg.fps is not None else "")
        _check_action_range(cfg.actions, sim, file_actions)
    truth = read_truth(cfg.truth, env_name, len(env.state_names), chosen) if cfg.truth else None
    if truth is not None and cfg.task != "control" and truth.get("video_sha256") not in (None, video_sha):
        raise RispError(f"{cfg.truth}: the ground truth of another video (its video_sha256 is not {cfg.video}'s); "
                        f"give the truth make-video wrote beside this video")
    if truth is not None and ref is not None:  # files from before video_sha256: at least the timeline must agree
        _check_truth_timeline(cfg, truth, ref)
    beside = truth_path(cfg.video)  # where make-video writes it
    if truth is None and cfg.task != "control" and os.path.isfile(beside):
        input_notes.append(f"{beside} lies beside the video (make-video's ground truth, which no solver reads): add "
                           f"--truth {beside} to see the errors against it")
    if cfg.task == "estimate" and sim.action_dim > 0 and cfg.actions is None:
        input_notes.append(f"without --actions the trajectory CSV has no command columns, which `risp-task diagnose` "
                           f"needs for the {env_name}: give the commands the video was filmed with as --actions A.csv")
    camera = read_camera(cfg.camera, ref.video.source_size if ref is not None else None, input_notes) \
        if cfg.camera else None
    if camera is not None and cfg.loss not in ("render", "pixelwise", "perceptual"):
        input_notes.append(f"--camera is used where the task renders: with the {cfg.loss} loss "
                           + ("only the plots show it" if cfg.plots else "and --no-plots it changes nothing"))
    ctx = Context(cfg=cfg, env=env, sim=sim, predictor=predictor, frames=frames_t, keep=keep, n_source=n_source,
                  fps=fps, k=k, predicted=predicted.double(), predicted_targets=predicted_targets.double(),
                  file_actions=file_actions, truth=truth, rng=task_rng(cfg.seed))
    problem = importlib.import_module(f"{__package__}.{cfg.task}").build(ctx)
    warnings = problem.info.pop("warnings", [])  # the task's own (control's initial state), kept for result.json
    if "init_scan" in problem.info:  # sysid --init scan: where the descent starts, and why
        scan = problem.info["init_scan"]
        start = problem.estimates()["initial_parameters"]
        echo(f"--init scan: starting from {', '.join(f'{n} = {v:.4g}' for n, v in start.items())}"
             f" (the least state loss of {scan['points']} points per parameter over its range"
             f"{'; one pass of coordinate search' if len(scan['parameters']) > 1 else ''})")
    if cfg.fit_params is None and problem.info.get("fitted_parameters"):  # imitate's default for this environment
        echo(f"identifying the {env_name}'s {', '.join(problem.info['fitted_parameters'])} with the actions "
             "(--params to give them, --no-fit-params for the nominal ones)")
    selection = problem.info.get("knot_selection")
    if selection is not None:  # --action-knots auto: what the cross-validation chose, and from what
        chosen = selection["chosen"]
        scores = ", ".join(f"{k}: {v:.4g}" for k, v in zip(selection.get("candidates", []),
                                                            selection.get("held_out_loss", [])))
        how = "--action-knots auto" if cfg.action_knots is not None else \
            f"the {env_name}'s command knots, chosen by cross-validation (--action-knots 0 for one row per frame)"
        echo(f"{how}: {'one row per frame' if chosen in (0, ctx.n_source) else f'{chosen} knots'}"
             + (f" (held-out loss by K: {scores})" if scores else f" ({selection['reason']})"))
    loss_frames = problem.frames if problem.frames is not None else keep

    renderer, render_threads = None, None
    if cfg.loss in ("render", "pixelwise", "perceptual") or cfg.plots:
        from risp_data.diff_render import StateRenderer, set_camera
        from risp_data.psi import nominal_rendering

        renderer = StateRenderer(drawn, resolution=predictor.resolution, spp=cfg.spp, primal_spp=cfg.primal_spp,
                                 config=nominal_rendering(env_name, "train"), boundary=cfg.gradient)
        render_threads = set_drjit_threads(cfg.render_threads)  # after the renderer: Mitsuba (and its LLVM) set up
        if camera is not None:
            set_camera(renderer.renderer, camera)
    truth_targets, truth_rows = None, None
    if truth is not None:
        truth_states = torch.tensor(truth["env_states"], dtype=torch.float64)
        if cfg.task == "control":  # the pictured state is the truth's last (make-video writes the whole run)
            truth_rows = [len(truth_states) - 1]
        else:  # one row per decoded frame, at the video's own rate (also with --fps)
            if len(truth_states) < ref.n_source:
                raise RispError(f"{cfg.truth}: {len(truth_states)} ground-truth states, the video has {ref.n_source} frames")
            truth_rows = ref.indices
        truth_targets = env.state_to_target(truth_states[truth_rows])
    timer = Timer()
    looks = render_looks(env_name, cfg.looks, cfg.seed)
    if looks is not None:  # written to result.json: the run names every look its loss read
        problem.info["looks"] = [{"domain": "train", "psi": look.psi.tolist(), "aux": look.aux} for look in looks]
    loss = make_loss(cfg.loss, env, loss_frames, predicted_targets.double(), truth_targets, frames_t,
                     predictor=predictor, renderer=renderer, timer=timer, features=features, residual=cfg.residual,
                     render_seed=cfg.seed, looks=looks)
    with torch.no_grad():
        initial_states = problem.states().detach().clone()
        initial_estimates = problem.estimates()
    warm = None
    if cfg.warm_start:  # the state loss first, then the render loss from there (docs/tasks.md §Warm start)
        state_loss = make_loss("state", env, loss_frames, predicted_targets.double(), None, None, residual=cfg.residual)
        warm = optimize(problem, state_loss, optimizer=cfg.optimizer, lr=cfg.lr, momentum=cfg.momentum,
                        iterations=cfg.warm_start, timer=timer, progress=cfg.progress)
    # One descent whose loss changes: the render iterations continue the warm start's optimiser.  A fresh RMSProp's
    # first steps are ~10·lr per coordinate whatever the gradient (its running mean of g² starts at 0), a kick that
    # throws the warm start's fit away; both losses live in the network's target space, so its step sizes suit both.
    history = optimize(problem, loss, optimizer=cfg.optimizer, lr=cfg.lr, momentum=cfg.momentum,
                       iterations=cfg.iterations, timer=timer, progress=cfg.progress, grow=cfg.grow_horizon,
                       frames=len(loss_frames), opt=warm["optimizer"] if warm else None)
    with torch.no_grad():
        final_states = problem.states().detach().clone()
    if looks is not None:  # the plots' strip shows the train domain's nominal look, as without --looks
        renderer.set_look(nominal_rendering(env_name, "train"))

    result = {
        "task": cfg.task, "env": env_name, "config": cfg.to_dict(), "seed": cfg.seed,
        "model": {"path": model_path, "sha256": predictor.sha256},  # of the bytes loaded, not the file now there
        "video": {"path": cfg.video, "sha256": video_sha, "frames": n_source, "kept": keep, "fps": fps,
                  **({"decoded_frames": ref.n_source, "decoded_kept": ref.indices, "decoded_fps": ref.source_fps}
                     if ref is not None else {})},
        "estimates": problem.estimates(), "initial": initial_estimates,
        "loss": history["loss"], "final_loss": history["final_loss"], "last_loss": history["last_loss"],
        "best_iteration": history["best_iteration"], **({"stopped": history["stopped"]} if "stopped" in history else {}),
        "timings": {"total_s": time.perf_counter() - started,
                    "seconds_per_iteration": history["seconds_per_iteration"], "sections_s": timer.seconds,
                    # what the arithmetic ran on: render-mode gradients' last bits follow Dr.Jit's count (null:
                    # nothing rendered)
                    "threads": {"torch": torch_threads, "drjit": render_threads}},
        "versions": versions(), "info": problem.info,
        # the other inputs' checksums, as the model's and the video's: a result names every file it read
        "inputs": {name: {"path": path, "sha256": sha256_file(path)} for name, path in
                   (("actions", cfg.actions), ("truth", cfg.truth), ("camera", cfg.camera), ("params", cfg.params),
                    ("initial_state", cfg.initial_state), ("mesh", cfg.mesh),
                    ("perceptual_weights", cfg.perceptual_weights)) if path and os.path.isfile(path)},
    }
    if cfg.task == "control":  # the state reached at the horizon (what the goal image pictures, if all went well)
        result["estimates"]["reached_env_state"] = final_states[-1].tolist()
        result["initial"]["reached_env_state"] = initial_states[-1].tolist()
    if "frames_compared" in history:
        result["frames_compared"], result["frames_in_loss"] = history["frames_compared"], history["frames_in_loss"]
    if warm is not None:
        result["warm_start"] = {"iterations": cfg.warm_start, "loss": warm["loss"], "final_loss": warm["final_loss"],
                                "seconds_per_iteration": warm["seconds_per_iteration"],
                                **({"stopped": warm["stopped"]} if "stopped" in warm else {})}
    if features is not None:
        result["info"] = {**problem.info, "perceptual_extractor": features.name}
    result["errors"] = _errors(cfg, env, sim, truth, truth_rows, loss_frames, initial_states, final_states, predicted,
                               initial_estimates, result["estimates"])
    warning = None
    if cfg.loss in IMAGE_LOSSES:
        result["view"], warning = _view(cfg, renderer, loss_frames, initial_states, final_states)
    stops = [f"{phase}: {h['stopped']}" for phase, h in (("warm start", warm), ("optimisation", history))
             if h is not None and h.get("stopped")]
    result["warnings"] = (input_notes + warnings + stops + ([warning] if warning else [])
                          + bound_warnings(result["estimates"]))
    folder = ResultFolder(out, cfg.overwrite)
    try:
        folder.write_json("result.json", result)
        if cfg.task == "estimate":
            _write_estimate_csv(folder.path("trajectory.csv"), ctx, final_states,
                                {"task": "risp-task estimate", "model": result["model"],
                                 "video": {k: result["video"][k] for k in ("path", "sha256", "frames", "fps")},
                                 # the run that made them, as result.json: the CSV may travel without its folder
                                 "seed": cfg.seed, "config": result["config"]})
        if cfg.task in ("imitate", "control"):
            from .inputs import write_actions

            write_actions(folder.path("actions.csv"), env_name, np.asarray(result["estimates"]["actions"]), fps)
        if cfg.plots:
            _plots(folder, cfg, env, ctx, loss_frames, initial_states, final_states, truth, history, renderer,
                   truth_fps=ref.source_fps if ref is not None else fps)
            if "init_scan" in problem.info:
                plot_scan(folder.path("init_scan.png"), problem.info["init_scan"],
                          result["estimates"]["parameters"], (truth or {}).get("params"), seed=cfg.seed)
        result["out"] = folder.commit()
    except BaseException:
        folder.discard()
        raise
    return result


#: Losses that compare renders of the simulated states with the video: blind where the object is out of view.
IMAGE_LOSSES = ("render", "pixelwise", "perceptual")


def _view(cfg, renderer, loss_frames, initial_states, final_states) -> tuple[dict, str | None]:
    """How much of the object the camera sees in each compared frame, before and after the optimisation
    (StateRenderer.in_view), and a warning line when the result has frames where it sees none of it: there an
    image loss has no gradient, and a rollout that left the view is not brought back (docs/tasks.md §Out of
    view)."""
    frames = list(loss_frames)
    before = renderer.in_view(initial_states[frames].float())
    after = renderer.in_view(final_states[frames].float())
    out = [f for f, v in zip(frames, after) if v == 0]
    view = {"frames": frames, "fraction_in_view_initial": before.tolist(), "fraction_in_view_final": after.tolist(),
            "frames_out_of_view_final": out}
    if not out:
        return view, None
    return view, (f"the result's simulated object is out of the camera's view in {len(out)} of the {len(frames)} "
                  f"compared frames (first: frame {out[0]}); the {cfg.loss} loss has no gradient there — try "
                  f"--loss state, or --grow-horizon (docs/tasks.md §Out of view)")


def _errors(cfg, env, sim, truth, truth_rows, loss_frames, initial_states, final_states, predicted, initial,
            final) -> dict:
    """Errors against the ground truth (when given; ``truth_rows``: its rows that go with the compared frames, for
    ``control`` the pictured last one): state RMSE per frame, parameter errors."""
    if truth is None:
        return {}
    from .simulate import wrap_angles

    angular = [n in ("yaw", "pitch", "roll") for n in env.state_names]
    true = torch.tensor(truth["env_states"], dtype=torch.float64)
    true = true[truth_rows]
    out = {}
    if cfg.task == "control":  # the goal is the truth's last state, the reached one the simulation's last frame
        def goal_rmse(states):
            return float(wrap_angles(states[-1] - true[-1], angular).pow(2).mean().sqrt())

        out = {"goal_rmse_initial": goal_rmse(initial_states), "goal_rmse_final": goal_rmse(final_states)}
    else:
        def rmse(states):
            return float(wrap_angles(states[loss_frames] - true, angular).pow(2).mean().sqrt())

        out = {"state_rmse_initial": rmse(initial_states), "state_rmse_final": rmse(final_states),
               "state_rmse_network": float(wrap_angles(predicted.double() - true, angular).pow(2).mean().sqrt())}
    if "parameters" in final and "params" in truth:  # sysid; imitate --fit-params
        p_true = truth["params"]
        out["parameter_error_initial"] = {n: abs(v - p_true[n]) for n, v in initial["parameters"].items() if n in p_true}
        out["parameter_error_final"] = {n: abs(v - p_true[n]) for n, v in final["parameters"].items() if n in p_true}
    return out


def held_commands(actions: np.ndarray, keep: list[int]) -> np.ndarray:
    """(len(keep), A): the command held from kept frame j to the next, the mean of the per-frame rows keep[j] …
    keep[j+1] − 1 (the last kept frame: to the end of the file).  diagnose holds a row's command until the next row
    (docs/measured-data.md), so with --every k one frame's command alone would stand for k frames of others."""
    keep = list(keep)
    ends = keep[1:] + [len(actions)]
    return np.stack([actions[a:max(b, a + 1)].mean(0) for a, b in zip(keep, ends)])


def _write_estimate_csv(path: str, ctx: Context, states: torch.Tensor, provenance: dict) -> None:
    """docs/measured-data.md columns for the quadrotor, cube and hand (the rod: t, z0 … z9).  The sidecar's
    ``estimated_by`` records that these are a network's readings of a video (which network, which video, the seed
    and settings), so that ``diagnose`` can say so when it cannot explain them (select.estimate_note)."""
    from risp_data.envs.rotations import euler_to_quat

    from ..measured import write_trajectory_csv

    s = states.detach().numpy()
    t = np.asarray(ctx.keep, np.float64) / ctx.fps
    cols: dict[str, np.ndarray] = {"t": t}
    held = held_commands(ctx.file_actions, ctx.keep) if ctx.file_actions is not None else None
    sim, env = ctx.sim, ctx.env
    sidecar = {"env": env.name, "estimated_by": provenance}
    if env.name in ("quadrotor", "cube"):
        q = euler_to_quat(*torch.from_numpy(s[:, 3:6]).unbind(-1)).numpy()
        q = q * np.where(np.cumsum(np.r_[1, np.sign((q[1:] * q[:-1]).sum(1))] < 0) % 2 == 1, -1, 1)[:, None]
        cols.update({n: s[:, i] for i, n in enumerate(("x", "y", "z"))})
        cols.update({n: q[:, i] for i, n in enumerate(("qw", "qx", "qy", "qz"))})
        if env.name == "quadrotor":
            sidecar.update({"mass": float(sim.default_params()[0, sim.param_index("mass")]), "gravity": 9.81})
            if ctx.file_actions is not None:
                cols.update({f"f{i}": held[:, i] for i in range(4)})
        else:
            sidecar.update({"side": sim.side, "mass": sim.mass, "gravity": 9.81})
    elif env.name == "hand":
        rates = np.gradient(s, t, axis=0) if len(t) > 1 else np.zeros_like(s)
        names = sim.state_names
        cols.update({n: s[:, i] for i, n in enumerate(names[:s.shape[1]])})
        cols.update({n: rates[:, i] for i, n in enumerate(names[s.shape[1]:])})
        if ctx.file_actions is not None:
            cols.update({f"u{i}": held[:, i] for i in range(held.shape[1])})
    else:
        cols.update({n: s[:, i] for i, n in enumerate(env.state_names)})
    write_trajectory_csv(path, cols, sidecar)


def _plots(folder, cfg, env, ctx, loss_frames, initial_states, final_states, truth, history, renderer, *,
           truth_fps: float) -> None:
    plot_loss(folder.path("loss.png"), history["loss"], f"{cfg.task} ({env.name}), loss {cfg.loss}",
              last=history["last_loss"], best=history["best_iteration"], seed=cfg.seed)
    t_keep = np.asarray(ctx.keep, np.float64) / ctx.fps
    if cfg.task == "control":
        t_sim = np.arange(len(final_states)) / ctx.fps
    elif cfg.task == "estimate":
        t_sim = t_keep
    else:
        t_sim = np.arange(len(final_states)) / ctx.fps
    curves = {"network N(video)": (t_keep if cfg.task != "control" else t_sim[-1:], ctx.predicted.numpy()),
              "initial": (t_sim, initial_states.numpy()), "optimized": (t_sim, final_states.numpy())}
    if truth is not None:
        true = np.asarray(truth["env_states"], np.float64)  # one row per decoded frame, at the video's own rate
        curves["truth"] = (np.arange(len(true)) / truth_fps, true) if cfg.task != "control" else (t_sim[-1:], true[-1:])
    plot_trajectories(folder.path("trajectory.png"), env.state_names, None, curves, seed=cfg.seed)
    if renderer is None:
        return
    pick = np.unique(np.linspace(0, len(loss_frames) - 1, min(STRIP_FRAMES, len(loss_frames))).round().astype(int))
    frames = [loss_frames[i] for i in pick]
    ref_rows = ctx.frames.numpy()[pick] if cfg.task != "control" else ctx.frames.numpy()
    with torch.no_grad():
        rows = {"reference": ref_rows,
                "initial": renderer(initial_states[frames].float(), seed=1).numpy(),
                "optimized": renderer(final_states[frames].float(), seed=1).numpy()}
    save_strip(folder.path("frames.png"), rows,
               note="initial, optimized: rendered in the train domain's nominal look (the reference row is the video)",
               seed=cfg.seed)
