"""The paper's published numbers (Ma et al., ICLR 2022), printed beside ours.

The `search` tool's stored pages hold the paper's abstract but not its tables, so the tables could not be
checked against the paper here.  What the project's own issue #8 quotes (state estimation, per-image L1) is
shown, marked as quoted and unverified; every other entry is ``None`` and printed as "not found".  Fill in
PAPER from the paper's Tables 1–4 (arXiv 2205.05678) when it is at hand, with the source in SOURCE.
"""

from __future__ import annotations

#: table -> env -> method -> published mean (None: not found)
PAPER: dict[str, dict[str, dict[str, float]]] = {
    "estimation": {
        "quadrotor": {"average": 0.599, "ours": 0.151},
        "cube": {"average": 0.592, "ours": 0.164},
    },
}
SOURCE = ("quoted in the project's issue #8 (\"The paper's cube and quadrotor errors (0.164 and 0.151 vs average "
          "0.592 and 0.599)\"), not verified against the paper; other entries not found by the search tool")


def published(table: str, env: str, method: str) -> float | None:
    return PAPER.get(table, {}).get(env, {}).get(method)
