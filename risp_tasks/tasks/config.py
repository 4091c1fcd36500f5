"""Task configuration: plain values in a frozen dataclass (saved in every result folder)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from risp_data.errors import RispError

LOSSES: tuple[str, ...] = ("render", "state", "oracle", "pixelwise", "perceptual")
INITS: tuple[str, ...] = ("default", "random", "track", "scan")
RESIDUALS: tuple[str, ...] = ("l2", "l1")  # how a frame's difference in the network's target space is weighed
NETWORK_LOSSES: tuple[str, ...] = ("render", "state", "oracle")  # the losses that take a residual norm


def default_residual(task: str, loss: str) -> str:
    """``l1`` for sysid's network-space losses, else ``l2`` (the paper's).  With the commands known and a few
    parameters free, a few gross misreadings of N pull a squared fit most; docs/tasks.md §Residual norm has the
    measurements behind the choice (sysid better with l1 on three systems, imitate not)."""
    return "l1" if task == "sysid" and loss in NETWORK_LOSSES else "l2"


AUTO_KNOTS = "auto"  # --action-knots auto: chosen by cross-validation over the video's frames (imitate.choose_knots)
AUTO_KNOTS_LOSSES: tuple[str, ...] = ("state", "render")  # the losses it takes: it scores by N's readings of the video

CONTROL_HORIZON = 10  # control's default frames to reach the pictured state


@dataclass(frozen=True)
class TaskConfig:
    """One task run.  ``loss``: ``render`` — ‖N(render(sim(θ))) − N(reference)‖² (the paper's loss, through
    network, renderer and simulator); ``state`` — ‖sim states − N(reference)‖², no rendering in the loop;
    ``oracle`` — against the ground-truth states of ``truth`` (evaluation only); ``pixelwise`` — ∇Sim's
    mean squared difference of render(sim(θ)) and the reference images in the train domain's nominal look (a
    baseline); ``perceptual`` — the mean over features of (F(render(sim(θ))) − F(reference images))² with F from
    ``perceptual_weights`` or the built-in filter bank (risp_tasks.tasks.features; a baseline).  Exact forms:
    risp_tasks.tasks.loop, docs/tasks.md §Losses."""

    task: str
    video: str  # video file, PNG folder, or (control) a target PNG
    out: str | None = None  # result folder (default results/<task>-<video stem>-seed<seed>)
    model: str | None = None  # risp-train checkpoint; None → the most recent runs/*/model.pt
    runs: str = "runs"
    env: str | None = None  # must match the model's; None → the model's
    loss: str = "state"
    init: str = "default"
    optimizer: str = "rmsprop"
    lr: float = 3e-3
    momentum: float = 0.5
    # l2: squared differences in the network's target space (the paper's); l1: absolute ones, robust to the
    # network's occasional large misreadings (loop.make_loss; docs/tasks.md §Residual norm); None: the task's
    # default (default_residual: l1 for sysid, l2 otherwise), resolved here so that result.json records it
    residual: str | None = None
    iterations: int = 100
    # render loss: first this many iterations of the state loss (same variables and optimiser settings), so that
    # the render-loss descent starts where N's per-frame estimates put it (docs/tasks.md §Warm start)
    warm_start: int = 0
    # horizon curriculum: over the first this many iterations the loss compares the first 2, 3, … kept frames, then
    # all of them (loop.horizon; docs/tasks.md §Horizon curriculum); 0: every iteration compares all frames
    grow_horizon: int = 0
    # imitate, control: K ≥ 2 knots of a piecewise-linear command per action instead of one row per frame
    # (imitate.knot_basis; docs/tasks.md §Smooth commands); 0: one row per frame (the paper's); imitate also takes
    # "auto": K chosen among a few by cross-validation over the video's frames (imitate.choose_knots); None: the
    # task's default (imitate.knots_setting: auto for imitate on the hand with the state or render loss, else 0)
    action_knots: int | str | None = None
    # imitate, control: the simulator's physical parameters where known — a JSON object {name: value}, a JSON file,
    # or a task's result.json (e.g. sysid's); None: the nominal ones (simulate.set_params)
    params: str | None = None
    # imitate: identify the environment's sysid parameters (sysid.IDENTIFIED) jointly with the actions, from the
    # middle of their ranges or the values --params gives (docs/tasks.md §Unknown physical parameters); None: yes
    # for the hand and the rod when --params is not given (imitate.fits_params), no for the quadrotor
    fit_params: bool | None = None
    seed: int = 0
    every: int = 1
    fps: float | None = None  # resample the video to this rate
    source_fps: float | None = None  # frame rate of a PNG folder; on a file it replaces the file's own (noted)
    actions: str | None = None  # actions CSV (sysid, estimate)
    truth: str | None = None  # ground-truth JSON (oracle loss and error reports only)
    camera: str | None = None  # camera JSON (intrinsics/extrinsics) replacing the environment's camera
    mesh: str | None = None  # vehicle mesh file (quadrotor) replacing the built-in one
    initial_state: str | None = None  # control: JSON with the initial simulator state
    horizon: int | None = None  # control: frames to reach the target (None: 10)
    # sysid, imitate: optimise the initial state read from the first two frames jointly (simulate.InitialState);
    # None: yes where the initial state is read from the video (quadrotor, cube, hand; the rod starts at rest)
    fit_initial_state: bool | None = None
    perceptual_weights: str | None = None  # local torchvision vgg16 state dict for --loss perceptual
    spp: int = 4  # samples per pixel of the differentiable renderer's gradient pass (render/pixelwise losses)
    # samples per pixel of the rendered frames the losses compare (the image N reads with --loss render); None: spp,
    # resolved here so that result.json records it (docs/tasks.md §Primal spp)
    primal_spp: int | None = None
    # render loss: N's readings of each simulated frame averaged over this many random train-domain looks drawn from
    # --seed (loop.make_loss; docs/tasks.md §Several looks); 1: the train domain's nominal look alone (the paper's)
    looks: int = 1
    gradient: str = "flat"  # boundary term of the renderer's gradient: flat (risp_data.flat_projective) | mitsuba
    threads: int = 1
    render_threads: int = 0  # Dr.Jit's CPU threads where the task renders (0: the CPUs this process may use)
    progress: bool = True
    plots: bool = True
    overwrite: bool = False  # replace an existing result folder at --out (only a task's: it holds result.json)

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise RispError(f"unknown loss {self.loss!r}; choose one of: {', '.join(LOSSES)}")
        if self.residual is None:
            object.__setattr__(self, "residual", default_residual(self.task, self.loss))
        if self.primal_spp is None:
            object.__setattr__(self, "primal_spp", self.spp)
        if self.task != "control":  # accepted by every task's command line so that this line can say whose they are
            given = [name for name, value in (("--initial-state", self.initial_state), ("--horizon", self.horizon))
                     if value is not None]
            if given:
                raise RispError(f"{' and '.join(given)}: control's (the start and the frames to reach a pictured "
                                f"state), not {self.task}'s")
        elif self.horizon is None:
            object.__setattr__(self, "horizon", CONTROL_HORIZON)
        if self.init not in INITS:
            raise RispError(f"unknown init {self.init!r}; choose one of: {', '.join(INITS)}")
        if self.residual not in RESIDUALS:
            raise RispError(f"unknown residual {self.residual!r}; choose one of: {', '.join(RESIDUALS)}")
        if self.residual != "l2" and self.loss not in NETWORK_LOSSES:
            raise RispError(f"--residual {self.residual} is for the render, state and oracle losses (differences of "
                            f"network readings); --loss {self.loss} compares images and stays squared")
        if self.optimizer not in ("rmsprop", "adam", "sgd"):
            raise RispError(f"unknown optimizer {self.optimizer!r}; choose one of: rmsprop, adam, sgd")
        for option, value, ok, rule in (
                ("--iterations", self.iterations, self.iterations >= 0, ">= 0"),
                ("--lr", self.lr, math.isfinite(self.lr) and self.lr > 0, "a finite number > 0"),
                ("--momentum", self.momentum, 0 <= self.momentum < 1, "in [0, 1): RMSProp's momentum; 1 or more diverges"),
                ("--every", self.every, self.every >= 1, ">= 1"),
                ("--horizon", self.horizon, self.horizon is None or self.horizon >= 1, ">= 1"),
                ("--spp", self.spp, self.spp >= 1, ">= 1"),
                ("--primal-spp", self.primal_spp, self.primal_spp >= 1, ">= 1"),
                ("--looks", self.looks, self.looks >= 1, ">= 1"),
                ("--render-threads", self.render_threads, self.render_threads >= 0, ">= 0 (0: automatic)"),
                ("--fps", self.fps, self.fps is None or (math.isfinite(self.fps) and self.fps > 0),
                 "a finite number > 0"),
                ("--source-fps", self.source_fps,
                 self.source_fps is None or (math.isfinite(self.source_fps) and self.source_fps > 0),
                 "a finite number > 0")):
            if not ok:
                raise RispError(f"{option} must be {rule}, got {value:g}")
        if self.init == "track" and self.task != "imitate":
            others = "default, random or scan" if self.task == "sysid" else "default or random"
            raise RispError(f"--init track is imitate's (a tracking controller along the video's estimated path), "
                            f"not {self.task}'s; choose {others}")
        if self.init == "scan" and self.task != "sysid":
            others = "default, random or track" if self.task == "imitate" else "default or random"
            raise RispError(f"--init scan is sysid's (a coarse scan of the loss over the parameters' ranges), not "
                            f"{self.task}'s; choose {others}")
        if self.init == "scan" and self.loss not in ("state", "render"):
            raise RispError(f"--init scan scans the state loss (the network's readings of the video), which --loss "
                            f"{self.loss} does not use: give --loss state or render, or --init default or random")
        if self.actions and self.task == "imitate":
            raise RispError("--actions: imitate finds the actions itself (give known commands to sysid or estimate; "
                            "known physical parameters to imitate with --params)")
        if self.seed < 0:
            raise RispError(f"--seed must be >= 0, got {self.seed}")
        if self.out is not None and not str(self.out).strip():  # "" silently meant the default folder
            raise RispError("--out is empty: give the result folder (or leave --out out for the default)")
        if self.grow_horizon < 0:
            raise RispError(f"--grow-horizon must be >= 0, got {self.grow_horizon}")
        if self.grow_horizon and self.task not in ("sysid", "imitate"):
            raise RispError(f"--grow-horizon is for sysid and imitate (a video's frames), not {self.task}")
        if isinstance(self.action_knots, str):
            if self.action_knots != AUTO_KNOTS:
                raise RispError(f"--action-knots must be a whole number (0, or >= 2) or {AUTO_KNOTS}, got "
                                f"{self.action_knots!r}")
            if self.task == "control":  # one pictured state: no frames to hold out
                raise RispError(f"--action-knots {AUTO_KNOTS} is imitate's (it holds out the video's frames); give "
                                "control a number")
            if self.init == "track":
                raise RispError(f"--action-knots {AUTO_KNOTS} chooses how the commands are parametrised; with --init "
                                "track the controller's reference path is optimised instead (leave one of them out)")
            if self.loss not in AUTO_KNOTS_LOSSES:  # it scores held-out frames by N's readings of the video
                raise RispError(f"--action-knots {AUTO_KNOTS} cross-validates on the network's readings of the video "
                                f"(--loss state or render); with --loss {self.loss} give a number")
        elif self.action_knots is not None and (self.action_knots < 0 or self.action_knots == 1):  # None: the
            # task's default, resolved where the environment is known (imitate.knots_setting)
            raise RispError(f"--action-knots must be 0 (one row per frame) or >= 2, got {self.action_knots}")
        if self.action_knots and self.task not in ("imitate", "control"):
            raise RispError(f"--action-knots is for imitate and control (the actions), not {self.task}")
        if self.task == "control" and self.horizon is not None and isinstance(self.action_knots, int) \
                and self.action_knots > self.horizon + 1:
            raise RispError(f"--action-knots {self.action_knots} is more than the {self.horizon + 1} action rows of "
                            f"--horizon {self.horizon} (one per frame, the start included): give at most "
                            f"{self.horizon + 1}, or 0 for one row per frame")
        if self.params and self.task not in ("imitate", "control"):
            raise RispError(f"--params is for imitate and control (sysid identifies them), not {self.task}")
        if self.fit_params is not None and self.task != "imitate":
            raise RispError(f"--fit-params is for imitate (sysid identifies the parameters itself), not {self.task}")
        if self.fit_params and self.init == "track":
            raise RispError("--fit-params needs the commands as variables; --init track optimises the controller's "
                            "reference path instead (leave one of them out)")
        if self.warm_start < 0:
            raise RispError(f"--warm-start must be >= 0, got {self.warm_start}")
        if self.warm_start and self.loss != "render":
            raise RispError(f"--warm-start is for --loss render (it runs the state loss first), not --loss {self.loss}")
        if self.looks > 1 and self.loss != "render":
            raise RispError(f"--looks averages the network's readings of the rendered frames (--loss render); "
                            f"--loss {self.loss} " + ("reads no rendered frame" if self.loss in ("state", "oracle")
                                                      else "compares images with the video, not readings"))
        if self.gradient not in ("flat", "mitsuba"):
            raise RispError(f"unknown --gradient {self.gradient!r}; choose one of: flat, mitsuba")
        if self.fit_initial_state is not None and self.task not in ("sysid", "imitate"):
            raise RispError(f"--fit-initial-state is for sysid and imitate, not {self.task}")
        if self.task == "control":  # one goal image: no video timeline, no commands to read
            given = [name for name, bad in (("--actions", self.actions), ("--every", self.every != 1),
                                            ("--source-fps", self.source_fps is not None)) if bad]
            if given:
                raise RispError(f"{', '.join(given)}: not used by control (one goal image; the commands are what it "
                                "finds, --fps sets the simulation's frame rate)")
        if self.loss == "oracle" and not self.truth:
            raise RispError("--loss oracle needs --truth (the reference video's ground-truth JSON)")

    def to_dict(self) -> dict:
        return asdict(self)
