"""Write frames as an animated GIF (Pillow, or imageio when installed) or an MP4 (imageio-ffmpeg)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import strict_keywords
from ..errors import InputError

SUFFIXES = (".gif", ".mp4")


def check_movie_path(out: str | os.PathLike) -> Path:
    """Raise unless ``out`` names a format that can be written here."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(f"animation {out} must end in .gif or .mp4")
    if suffix == ".mp4":
        from .._optional import require

        for module in ("imageio.v2", "imageio_ffmpeg"):
            require(module, f"writing {out.name} (a .gif needs nothing more)")
    return out


@strict_keywords
def write_movie(out: str | os.PathLike, frames: Sequence[np.ndarray], fps: float = 10.0) -> Path:
    """Write (H, W, 3) uint8 frames to ``out`` (.gif or .mp4), atomically."""
    out = check_movie_path(out)
    if not frames:
        raise InputError(f"no frame to write to {out}")
    from ..io._files import atomic_output

    with atomic_output(out) as tmp:
        if out.suffix.lower() == ".mp4":
            import imageio.v2 as iio

            writer: Any = iio.get_writer(tmp, fps=fps, macro_block_size=1)
            with writer:
                for f in frames:
                    writer.append_data(np.asarray(f, dtype=np.uint8))
        else:
            from PIL import Image

            imgs = [Image.fromarray(np.asarray(f, dtype=np.uint8)).convert("RGB") for f in frames]
            pal = [im.quantize(colors=255, method=Image.Quantize.MEDIANCUT) for im in imgs]
            pal[0].save(
                tmp,
                format="GIF",
                save_all=True,
                append_images=pal[1:],
                duration=int(round(1000.0 / fps)),
                loop=0,
                optimize=False,
            )

    return out
