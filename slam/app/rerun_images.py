"""Arrays for Rerun components: colour maps, and colour and depth images shrunk and compressed."""

from __future__ import annotations

import functools

import numpy as np


def colormap(name: str, values: np.ndarray) -> np.ndarray:
    """(N,) values in [0, 1] -> (N, 3) uint8 colours of a matplotlib colormap (256 levels)."""
    lut = _colormap_table(name)
    levels = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0) * (len(lut) - 1)
    return lut[np.rint(levels).astype(np.intp)]


@functools.cache
def _colormap_table(name: str) -> np.ndarray:
    """The (256, 3) uint8 table of a matplotlib colormap, built once per process."""
    from matplotlib import colormaps

    return np.asarray(colormaps[name](np.linspace(0.0, 1.0, 256), bytes=True))[:, :3]


def shrink(image: np.ndarray, scale: int, interpolation: int) -> np.ndarray:
    """Shrink by the integer ``scale`` (nearest for depth, so invalid zeros never blend)."""
    import cv2

    if scale == 1:
        return image
    size = (image.shape[1] // scale, image.shape[0] // scale)
    return cv2.resize(image, size, interpolation=interpolation)


def encode_rgb(rgb: np.ndarray, scale: int, jpeg_quality: int) -> bytes | np.ndarray:
    """An RGB image shrunk by ``scale`` as JPEG bytes; the shrunk BGR pixels when encoding
    fails."""
    import cv2

    bgr = cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)  # beats [::-1]
    bgr = shrink(bgr, scale, cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    return jpeg.tobytes() if ok else bgr


def encode_depth(depth_m: np.ndarray, scale: int, as_png: bool) -> bytes | np.ndarray:
    """Depth in metres shrunk by ``scale``: a 16-bit millimetre PNG when ``as_png`` (and it
    encodes), else float32 metres; NaN and infinities become 0 (invalid)."""
    import cv2

    depth_m = shrink(np.asarray(depth_m, dtype=np.float32), scale, cv2.INTER_NEAREST)
    depth_m = np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0)
    if as_png:
        depth_mm = np.clip(np.round(depth_m * 1000.0), 0, 65535).astype(np.uint16)
        ok, png = cv2.imencode(".png", depth_mm)
        if ok:
            return png.tobytes()
    return depth_m
