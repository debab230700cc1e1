"""Writing a reference render to disk: one EXR with every pass, plus a PNG preview.

EXR channels (linear radiance, float32):

- ``R, G, B, A``: the defocused image (premultiplied; A = coverage);
- ``AllInFocus.R/G/B/A``: the pinhole view;
- ``Depth.Z``: planar depth, 1e10 where no card (as Cycles' Z pass);
- ``Disparity.Y``: 1/Z, 0 where no card;
- ``Layer.Y``: index of the front-most card with alpha >= 0.5, -1 where none;
- ``Hit.<card>.A``: each card's alpha at the pixel centre (the per-pixel hit layers).

The header attribute ``mpib`` holds JSON: the engine, its settings, timings and camera.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr
from mpib_validate.runtime.io.preview import write_png
from mpib_validate.cards.scene import Scene
from mpib_validate.cards.trace import TraceResult


def result_channels(result: TraceResult, scene: Scene) -> dict[str, np.ndarray]:
    ch = channels_from_rgba(result.bokeh)
    ch.update(channels_from_rgba(result.all_in_focus, "AllInFocus."))
    ch["Depth.Z"] = result.depth
    ch["Disparity.Y"] = result.disparity
    ch["Layer.Y"] = result.layer.astype(np.float32)
    for card, alpha in zip(scene.cards, result.card_alpha):
        ch[f"Hit.{card.name}.A"] = alpha
    return ch


def write_render(path: str | os.PathLike, result: TraceResult, scene: Scene,
                 preview: bool = True) -> list[Path]:
    """Write the EXR (atomically) and, with ``preview``, a PNG beside it; returns the paths."""
    path = Path(path)
    meta = dict(result.meta)
    meta["camera"] = scene.camera.to_dict()
    meta["cards"] = [c.name for c in scene.cards]
    write_exr(path, result_channels(result, scene), attributes={"mpib": json.dumps(meta)})
    written = [path]
    if preview:
        png = path.with_suffix(".png")
        write_png(png, result.bokeh[..., :3])
        written.append(png)
    return written
