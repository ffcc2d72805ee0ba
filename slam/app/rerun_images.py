"""Arrays as Rerun components: colour maps, and colour and depth images shrunk and compressed."""

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


def encode_rgb(rgb: np.ndarray, scale: int, jpeg_quality: int) -> object:
    """An RGB image shrunk by ``scale`` as a JPEG ``EncodedImage`` (raw when encoding fails)."""
    import cv2
    import rerun as rr

    bgr = cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)  # beats [::-1]
    bgr = shrink(bgr, scale, cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        return rr.Image(bgr, color_model="BGR")
    return rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg")


def encode_depth(depth_m: np.ndarray, scale: int, as_png: bool) -> object:
    """Depth in metres shrunk by ``scale``: a 16-bit millimetre PNG when ``as_png`` (and it
    encodes), else a float32 ``DepthImage``; NaN and infinities become 0 (invalid)."""
    import cv2
    import rerun as rr

    depth_m = shrink(np.asarray(depth_m, dtype=np.float32), scale, cv2.INTER_NEAREST)
    depth_m = np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0)
    if as_png:
        depth_mm = np.clip(np.round(depth_m * 1000.0), 0, 65535).astype(np.uint16)
        ok, png = cv2.imencode(".png", depth_mm)
        if ok:
            return rr.EncodedDepthImage(png.tobytes(), media_type="image/png", meter=1000.0)
    return rr.DepthImage(depth_m, meter=1.0)
