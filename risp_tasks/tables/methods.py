"""Methods as configuration: what each row of a table does (the perceptual loss's feature extractors:
risp_tasks/tasks/features.py).

Every method is one :class:`Method` value; the cells read its fields and never branch on copied scripts.

* ``average``      — the training set's mean quantity (estimation: target_to_state of the mean target over the
                     training shards; sysid: the middle of the parameter's sampling range; imitation/control:
                     the neutral actions, x = 0) — no optimisation.
* ``random``       — one seeded draw from the sampling distribution (states: the environment's sampler;
                     parameters: uniform in the paper's range; actions: x ~ U(−1, 1)) — no optimisation.
* ``pixelwise``    — ∇Sim: ‖R(s) − I‖² through risp_data.diff_render, rendered in the train domain's nominal look.
* ``perceptual``   — ‖F(R(s)) − F(I)‖² with F a convolutional feature extractor (risp_tasks.tasks.features.feature_extractor).
* ``ours-no-grad`` — RISP's loss ‖N(R(s)) − N(I)‖² with N trained with ``--reg none``.
* ``ours``         — the same with N trained with the table's regularizer (``TableConfig.reg``, default
                     risp-train's default regularizer: config.default_reg).
* ``ours-state``   — the ``ours`` network read once per reference frame, and the simulated states fitted to
                     those readings: ‖s(θ) − N(I)‖ (the tasks' ``state`` loss, ``risp-task``'s default; no rendering
                     in the loop).  Estimation: N/A, it is ``ours`` there (N(I) itself).
* ``oracle``       — the ground-truth states (estimation: zero error by definition; tasks: the ``oracle`` loss).
"""

from __future__ import annotations

from dataclasses import dataclass

from risp_data.errors import RispError


@dataclass(frozen=True)
class Method:
    name: str
    loss: str | None  # None (no optimisation) | pixelwise | perceptual | render | state | oracle
    network: str | None = None  # None | "none" (ours-no-grad) | "reg" (ours: TableConfig.reg)
    init: str = "default"  # initial guess of the optimising methods: default (average) | random
    description: str = ""


METHOD_SPECS: dict[str, Method] = {m.name: m for m in (
    Method("average", None, description="training set's mean quantity"),
    Method("random", None, init="random", description="a draw from the sampling distribution"),
    Method("pixelwise", "pixelwise", description="∇Sim: image loss, train domain's nominal look"),
    Method("perceptual", "perceptual", description="feature loss of a conv extractor"),
    Method("ours-no-grad", "render", network="none", description="RISP network trained with --reg none"),
    Method("ours", "render", network="reg", description="RISP network trained with the regularizer"),
    Method("ours-state", "state", network="reg", description="the `ours` network, state loss (risp-task's default)"),
    Method("oracle", "oracle", description="ground-truth states"),
)}
METHODS: tuple[str, ...] = tuple(METHOD_SPECS)


def get_method(name: str) -> Method:
    if name not in METHOD_SPECS:
        raise RispError(f"unknown method {name!r}; choose one of: {', '.join(METHODS)}")
    return METHOD_SPECS[name]


def estimation_network(name: str) -> str | None:
    """The network an estimation cell of method ``name`` reads: its own, except `ours-state`'s, whose cell is N/A
    there (it would be `ours` again) and reads nothing."""
    m = get_method(name)
    return None if m.loss == "state" else m.network

