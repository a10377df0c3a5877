"""The leaderboard website: server-rendered pages, charts, track plots and the replay viewer.

``create_app`` includes :data:`web_router` (the HTML pages) and calls :func:`mount` for the
static mounts (``/static``, ``/viewer``, ``/replays``). Nothing here imports pybullet, torch
or viser.
"""

from leaderboard.web.pages import web_router
from leaderboard.web.viewer import mount

__all__ = ["mount", "web_router"]
