"""One rendered sample as it travels from the renderer to the shard writers and back out of the readers."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

KEY_DIGITS = 8  # sample keys look like ``s00001234``; webdataset splits keys at the first dot, so no dots


def sample_key(index: int) -> str:
    """The webdataset key of global sample ``index`` (no dots: webdataset splits keys at the first one)."""
    return f"s{index:0{KEY_DIGITS}d}"


@dataclass(frozen=True)
class Sample:
    """A rendered sample: the image I, its Jacobian stack J = [∂I/∂ψ_1 … ∂I/∂ψ_K], state s and ψ.

    ``image`` (H, W, 3) float32 linear RGB; ``jacobian`` (K, H, W, 3) float32 or None (eval shards);
    ``state`` (S,) float64; ``psi`` (K,) float64; ``meta`` a JSON-serializable dict (see docs/formats.md).
    """

    index: int
    image: np.ndarray
    jacobian: np.ndarray | None
    state: np.ndarray
    psi: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        return sample_key(self.index)

    def as_dict(self) -> dict[str, Any]:
        """The reader-side representation shared by the webdataset and zarr readers."""
        return {
            "key": self.key,
            "image": self.image,
            "jacobian": self.jacobian,
            "state": self.state,
            "psi": self.psi,
            "meta": self.meta,
        }


def stack_samples(samples: list[Sample]) -> dict[str, np.ndarray | None]:
    """Stack a shard's samples into (n, ...) arrays, checking that their shapes agree."""
    if not samples:
        raise ValueError("cannot stack an empty shard")
    out: dict[str, np.ndarray | None] = {
        "images": np.stack([s.image for s in samples]).astype(np.float32, copy=False),
        "states": np.stack([s.state for s in samples]).astype(np.float64, copy=False),
        "psi": np.stack([s.psi for s in samples]).astype(np.float64, copy=False),
        "jacobians": None,
    }
    if samples[0].jacobian is not None:
        out["jacobians"] = np.stack([s.jacobian for s in samples]).astype(np.float32, copy=False)
    return out
