"""Perception uncertainty: lidar noise and dropout, camera-image jitter (DeepRacer's set).

Pure functions of per-car arrays and a seeded generator. The *levels* (noise std, dropout
probability, brightness offset, …) come from a :class:`arena.uncertainty.Perturbation`, one
per car; the random parts (which rays drop, the pixel noise, where the shadow falls) are
drawn here every frame.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def jitter_lidar(
    ranges: NDArray[np.floating],
    noise_std: FloatArray,
    dropout: FloatArray,
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    """Noisy lidar ranges.

    Args:
        ranges: (n_cars, n_rays) ranges normalised to [0, 1] (1 = nothing within range).
        noise_std: (n_cars,) std of additive Gaussian noise, normalised range units.
        dropout: (n_cars,) probability that a ray returns nothing (reads 1).
        rng: the env's generator.

    Returns:
        (n_cars, n_rays) float32 in [0, 1].
    """
    noisy = ranges + rng.standard_normal(ranges.shape) * noise_std[:, None]
    dropped = rng.random(ranges.shape) < dropout[:, None]
    return np.clip(np.where(dropped, 1.0, noisy), 0.0, 1.0).astype(np.float32)


def _rotate_hue(rgb: FloatArray, turns: float) -> FloatArray:
    """Rotate the hue of an RGB image (H, W, 3) in [0, 255] by ``turns`` (about the grey axis)."""
    angle = 2.0 * np.pi * turns
    cos, sin = np.cos(angle), np.sin(angle)
    k = 1.0 / 3.0
    root = np.sqrt(k)
    # Rodrigues rotation about (1, 1, 1)/√3: keeps grey grey, turns the colour wheel.
    m = np.array(
        [
            [cos + k * (1 - cos), k * (1 - cos) - root * sin, k * (1 - cos) + root * sin],
            [k * (1 - cos) + root * sin, cos + k * (1 - cos), k * (1 - cos) - root * sin],
            [k * (1 - cos) - root * sin, k * (1 - cos) + root * sin, cos + k * (1 - cos)],
        ]
    )
    return rgb @ m.T


def jitter_image(
    image: NDArray[np.uint8],
    *,
    brightness: float,
    contrast: float,
    hue: float,
    noise_std: float,
    shift: float,
    shadow: float,
    rng: np.random.Generator,
) -> NDArray[np.uint8]:
    """One camera image with DeepRacer-style jitter.

    Args:
        image: (H, W, C) uint8, C = 1 (grey) or 3 (RGB).
        brightness: added, as a fraction of 255.
        contrast: multiplies the distance from mid-grey (128).
        hue: turns of hue rotation (RGB only; a grey image has no hue).
        noise_std: std of Gaussian pixel noise, grey levels.
        shift: horizontal shift, px (rounded; + moves the picture right, edge repeated).
        shadow: darkness 0–1 of a vertical band a quarter of the width wide, at a random
            place (0: none).
        rng: the env's generator (noise and shadow position).

    Returns:
        (H, W, C) uint8.
    """
    img = image.astype(np.float64)
    if hue and img.shape[-1] == 3:
        img = _rotate_hue(img, hue)
    img = (img - 128.0) * contrast + 128.0 + 255.0 * brightness
    px = round(shift)
    if px:
        img = np.roll(img, px, axis=1)
        if px > 0:
            img[:, :px] = img[:, px : px + 1]
        else:
            img[:, px:] = img[:, px - 1 : px]
    if shadow > 0.0:
        width = img.shape[1]
        band = max(1, width // 4)
        left = int(rng.integers(0, width - band + 1))
        img[:, left : left + band] *= 1.0 - shadow
    if noise_std > 0.0:
        img = img + rng.standard_normal(img.shape) * noise_std
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
