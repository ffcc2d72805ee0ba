"""Plain helpers shared by several test files (fixtures live in ``tests/conftest.py``)."""

from __future__ import annotations

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_pixels(path) -> np.ndarray:
    """The RGB pixels (uint8) of the PNG at ``path``."""
    from matplotlib import image

    with open(path, "rb") as stream:
        assert stream.read(8) == PNG_SIGNATURE, path
    return (image.imread(path)[..., :3] * 255).round().astype(np.uint8)


def figure_pixels(figure) -> np.ndarray:
    """The RGB pixels (uint8) of a matplotlib figure drawn on its Agg canvas."""
    figure.canvas.draw()
    return np.asarray(figure.canvas.buffer_rgba())[..., :3].copy()


def assert_png_shows(path, figure) -> None:
    """The PNG at ``path`` is ``figure``, pixel for pixel (a figure drawn from the data the
    plot should show: any other data, style or layout changes pixels)."""
    np.testing.assert_array_equal(png_pixels(path), figure_pixels(figure))


def colour_mask(pixels: np.ndarray, colour, tolerance: int = 24) -> np.ndarray:
    """Where ``pixels`` (H, W, 3 uint8) are within ``tolerance`` of a matplotlib colour."""
    from matplotlib.colors import to_rgb

    target = np.round(np.asarray(to_rgb(colour)) * 255)
    return np.abs(pixels.astype(int) - target).max(axis=-1) <= tolerance
