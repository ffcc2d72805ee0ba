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


def shrink(image: np.ndarray, scale: int) -> np.ndarray:
    """Shrink by the integer ``scale`` with area averaging (colour images)."""
    import cv2

    if scale == 1:
        return image
    size = (image.shape[1] // scale, image.shape[0] // scale)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def encode_rgb(rgb: np.ndarray, scale: int, jpeg_quality: int) -> bytes | np.ndarray:
    """An RGB image shrunk by ``scale`` as JPEG bytes; the shrunk BGR pixels when encoding
    fails."""
    import cv2

    bgr = cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)  # beats [::-1]
    bgr = shrink(bgr, scale)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    return jpeg.tobytes() if ok else bgr


def encode_depth(depth_m: np.ndarray, scale: int) -> bytes | np.ndarray:
    """Depth in metres shrunk by ``scale`` (every ``scale``-th pixel, so invalid zeros never
    blend): a 16-bit millimetre PNG, or float32 metres when that does not encode; NaN and
    infinities become 0 (invalid)."""
    import cv2

    depth_m = np.asarray(depth_m, dtype=np.float32)
    height, width = (depth_m.shape[0] // scale) * scale, (depth_m.shape[1] // scale) * scale
    depth_m = depth_m[:height:scale, :width:scale]  # what cv2.INTER_NEAREST picks, unresampled
    depth_m = np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0)
    depth_mm = np.clip(np.round(depth_m * 1000.0), 0, 65535).astype(np.uint16)
    ok, png = cv2.imencode(".png", depth_mm)
    return png.tobytes() if ok else depth_m
