"""Top-down RGB rendering of a track and its cars (PIL; headless, no OpenGL)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from arena.colours import car_colour
from arena.walls import Walls
from tracks import Track
from tracks.geometry import signed_area

GROUND = (92, 128, 84)
ROAD = (70, 70, 74)
WALL = (235, 235, 235)
START = (255, 255, 255)


class TopDownRenderer:
    """Draws cars over a cached image of the track.

    Args:
        track: the track.
        walls: its walls (drawn as lines).
        size: image width and height, pixels.
    """

    def __init__(self, track: Track, walls: Walls, size: int = 480) -> None:
        from PIL import Image, ImageDraw  # noqa: PLC0415 - only an env that renders needs PIL

        self.size = size
        pts = np.vstack([walls.left, walls.right])
        lo, hi = pts.min(axis=0) - 1.0, pts.max(axis=0) + 1.0
        self.scale = (size - 1) / float(max(hi - lo))
        self.origin = lo
        img = Image.new("RGB", (size, size), GROUND)
        draw = ImageDraw.Draw(img)
        loops = sorted((track.left_border, track.right_border), key=lambda b: -abs(signed_area(b)))
        draw.polygon(self._px(loops[0]), fill=ROAD)
        draw.polygon(self._px(loops[1]), fill=GROUND)
        for wall in (walls.left, walls.right):
            draw.line([*self._px(wall), self._px(wall[:1])[0]], fill=WALL, width=2)
        gate = track.gates([0.0])[0]
        draw.line(self._px(gate), fill=START, width=3)
        self.background = img

    def _px(self, xy: NDArray[np.float64]) -> list[tuple[float, float]]:
        """World points (m, 2) → pixel tuples (y axis pointing down)."""
        p = (np.asarray(xy) - self.origin) * self.scale
        return [(float(x), float(self.size - 1 - y)) for x, y in p]

    def render(self, corners: NDArray[np.float64], active: NDArray[np.bool_]) -> NDArray[np.uint8]:
        """(size, size, 3) uint8 image with every active car's rectangle (n, 4, 2) m."""
        from PIL import ImageDraw  # noqa: PLC0415 - loaded by __init__ already

        img = self.background.copy()
        draw = ImageDraw.Draw(img)
        for i, (box, on) in enumerate(zip(corners, active, strict=True)):
            if on:
                draw.polygon(self._px(box), fill=car_colour(i), outline=(0, 0, 0))
                nose = 0.5 * (box[0] + box[3])
                draw.line(self._px(np.stack([box.mean(axis=0), nose])), fill=(0, 0, 0), width=2)
        return np.asarray(img, dtype=np.uint8)
