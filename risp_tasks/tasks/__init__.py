"""Tasks that go from a video to states, physical parameters and actions (docs/tasks.md).

One module per task — :mod:`.estimate`, :mod:`.sysid`, :mod:`.imitate`, :mod:`.control` — each turning a
:class:`.config.TaskConfig` into a :class:`.loop.Problem` (what is optimised and how it becomes a
trajectory); :mod:`.loop` holds the one optimisation loop and the loss modes, :mod:`.inputs` the model,
video, actions and camera readers, :mod:`.results` the result folder, :mod:`.reference` the maker of
reference videos.  A *method* (loss mode, initialisation, optimiser) is configuration, never a copy of a
script.
"""

TASKS: tuple[str, ...] = ("estimate", "sysid", "imitate", "control")
