"""The 3D race scene in viser: one renderer for the site's replays, local replays and live races.

:func:`build_scene` adds the static scene (track ribbon, red/white kerbs, start/finish line,
ground grid) and one node per car: the car's body (to scale, with a dark nose), a **marker**
(a flat arrow in the car's colour, sized to the track: :func:`marker_length`, at least
``track size / MARKER_FRACTION`` m, so every car is ≳ 15 px long at 1280×720 in the default
view, where a true-scale 0.5 m car is 3–5 px), a thin **pole** in the car's colour and, on
top of it, a **label** ``P<position> <name>``. Pole heights are staggered by where the cars
stand on the screen at the start (:func:`label_heights`), so the labels do not overlap on the
grid. A **standings board** (a label at the track's top-left corner: the leader's lap
``Lap 2/3`` and every car's position and lap) and the car labels are updated as the race
goes (:class:`SceneCars`, from :class:`arena.standings.StandingsTracker`). The initial camera
(:func:`fit_view`) looks down at 55° on the whole track, as close as fits a 16:9 viewport.

:class:`LiveScene` runs a viser server and moves the cars as a race runs or a replay plays
(``slipstream race --watch``, ``slipstream replay``), with a *Follow* dropdown that makes
the camera chase one car; :mod:`submissions.viser_replay` records the same scene into
``.viser`` files for the site (there, the player's own orbit/zoom and the race page's 2D
map follow a car).

viser is optional (the ``eval`` extra) and imported only when a scene is built.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.sim import CarParams
from arena.standings import Standing, StandingsTracker, race_laps, standings_text
from tracks import Track

FloatArray = NDArray[np.float64]

ROAD_COLOUR = (70, 70, 75)
KERB_COLOURS = ((220, 30, 30), (245, 245, 245))
KERB_RUN = 3  # border segments per kerb stripe
KERB_WIDTH = 0.08  # m, drawn line width
SURFACE_Z = 0.0  # m
LINE_Z = 0.01  # m: lines just above the road, so they are not z-fighting with it
MARKER_FRACTION = 24.0  # the marker is at least the track's size / this, m
VIEW_ELEVATION_DEG = 55.0  # the default camera looks down this steeply
VIEW_FOV_DEG = 50.0  # its vertical field of view
VIEW_MARGIN = 0.92  # the track fills at most this much of the frame (NDC units)
LABEL_STEP_PX = 17.0  # px between stacked car labels (a label line is ~16 px tall)


def yaw_to_wxyz(yaw: FloatArray) -> FloatArray:
    """Quaternions (..., 4) [w, x, y, z] of rotations by ``yaw`` rad about +z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zero = np.zeros_like(half)
    return np.stack([np.cos(half), zero, zero, np.sin(half)], axis=-1)


def marker_length(track: Track, car: CarParams) -> float:
    """Length (m) of a car's marker: the car's length, or more on a big track.

    >>> from tracks import load_track
    >>> round(marker_length(load_track("oval"), CarParams()), 2) > CarParams().length
    True
    """
    xmin, ymin, xmax, ymax = track.bounds
    size = max(xmax - xmin, ymax - ymin)
    return max(car.length, size / MARKER_FRACTION)


def track_ribbon(track: Track) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
    """The road surface as a closed triangle strip: vertices (2N, 3) m and faces (2N, 3)."""
    n = track.n_points
    verts = np.zeros((2 * n, 3), dtype=np.float32)
    verts[0::2, :2] = track.left_border
    verts[1::2, :2] = track.right_border
    verts[:, 2] = SURFACE_Z
    i = np.arange(n)
    j = (i + 1) % n
    a, b, c, d = 2 * i, 2 * i + 1, 2 * j, 2 * j + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)]).astype(np.uint32)
    return verts, faces


def kerb_segments(border: FloatArray) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """A closed border polyline (N, 2) m as segments (N, 2, 3) and red/white colours (N, 2, 3)."""
    pts = np.concatenate([border, np.full((len(border), 1), LINE_Z)], axis=1)
    seg = np.stack([pts, np.roll(pts, -1, axis=0)], axis=1).astype(np.float32)
    stripe = (np.arange(len(seg)) // KERB_RUN) % 2
    cols = np.asarray(KERB_COLOURS, dtype=np.uint8)[stripe]
    return seg, np.repeat(cols[:, None, :], 2, axis=1)


def _arrow(length: float) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
    """A flat arrow (a thin triangular prism) pointing +x, ``length`` m long."""
    half_w, top = 0.3 * length, 0.04 * length
    tri = np.array([[0.5 * length, 0.0], [-0.5 * length, half_w], [-0.5 * length, -half_w]])
    verts = np.concatenate(
        [np.column_stack([tri, np.zeros(3)]), np.column_stack([tri, np.full(3, top)])]
    ).astype(np.float32)
    faces = np.array(
        [[0, 1, 2], [3, 5, 4], [0, 3, 1], [1, 3, 4], [1, 4, 2], [2, 4, 5], [2, 5, 0], [0, 5, 3]],
        dtype=np.uint32,
    )
    return verts, faces


@dataclass(frozen=True)
class View:
    """A camera that frames the whole track: ``position`` and ``look_at`` (3,) m, ``fov`` rad.

    ``px_per_m``: screen pixels per metre at the look-at point in a 720 px tall viewport.
    """

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    fov: float
    px_per_m: float


def fit_view(track: Track, aspect: float = 16 / 9) -> View:
    """The camera that shows the whole track as large as fits a viewport of ``aspect``.

    It looks down at :data:`VIEW_ELEVATION_DEG` from the side of the track's shorter extent
    (so the longer one lies across the screen), and stands as close as lets every border
    point stay within :data:`VIEW_MARGIN` of the frame (perspective included).
    """
    xmin, ymin, xmax, ymax = track.bounds
    centre = np.array([0.5 * (xmin + xmax), 0.5 * (ymin + ymax), 0.0])
    elev = np.radians(VIEW_ELEVATION_DEG)
    horiz = np.array([0.0, 1.0, 0.0]) if xmax - xmin >= ymax - ymin else np.array([-1.0, 0.0, 0.0])
    forward = np.cos(elev) * horiz + np.array([0.0, 0.0, -np.sin(elev)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    pts = np.concatenate([track.left_border, track.right_border])
    pts = np.column_stack([pts, np.zeros(len(pts))]) - centre
    fov = np.radians(VIEW_FOV_DEG)
    tan = np.tan(0.5 * fov)

    def fits(dist: float) -> bool:
        rel = pts + dist * forward  # the camera is at centre - dist * forward
        depth = rel @ forward
        if np.any(depth <= 0):
            return False
        x = np.abs(rel @ right) / (depth * tan * aspect)
        y = np.abs(rel @ up) / (depth * tan)
        return bool(max(x.max(), y.max()) <= VIEW_MARGIN)

    lo, hi = 0.1, 1.0
    while not fits(hi):
        hi *= 2.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    position = centre - hi * forward
    px_per_m = 720.0 / (2.0 * hi * tan)
    return View(
        tuple(float(v) for v in position),  # type: ignore[arg-type]
        tuple(float(v) for v in centre),  # type: ignore[arg-type]
        float(fov),
        float(px_per_m),
    )


def project(view: View, points: FloatArray, width: int = 1280, height: int = 720) -> FloatArray:
    """Screen pixels (M, 2) [x right, y down] of world points (M, 3) m in ``view``.

    A pinhole camera as three.js draws it: vertical field of view ``view.fov``, the viewport
    ``width`` × ``height`` px. Points behind the camera come out as NaN.
    """
    pos = np.asarray(view.position)
    forward = np.asarray(view.look_at) - pos
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = np.asarray(points, dtype=np.float64) - pos
    depth = rel @ forward
    depth = np.where(depth > 0, depth, np.nan)
    tan = np.tan(0.5 * view.fov)
    x = (rel @ right) / (depth * tan * width / height)
    y = (rel @ up) / (depth * tan)
    return np.column_stack([(x + 1.0) * 0.5 * width, (1.0 - y) * 0.5 * height])


def label_heights(view: View, start: FloatArray, step_px: float, base: float) -> FloatArray:
    """Label heights (n,) m above each car so that labels do not overlap on the start grid.

    Cars are taken from the lowest on the screen (in ``view``, at their ``start`` poses
    (n, 3); NaN: unknown) to the highest; each label goes at least ``base`` m above its car
    and high enough that its anchor is drawn ``step_px`` pixels above every label placed
    before it (solved on the exact projection, so perspective cannot squeeze two together).
    """
    xy = np.nan_to_num(np.asarray(start, dtype=np.float64)[:, :2])
    n = len(xy)

    def screen_y(i: int, h: float) -> float:
        return float(project(view, np.array([[xy[i, 0], xy[i, 1], h]]))[0, 1])

    ground = project(view, np.column_stack([xy, np.zeros(n)]))[:, 1]
    heights = np.full(n, float(base))
    top = np.inf  # the highest anchor placed so far (smallest screen y)
    for i in np.argsort(-np.nan_to_num(ground), kind="stable"):  # lowest on screen first
        if np.isfinite(top) and screen_y(i, base) > top - step_px:
            lo, hi = base, base + 1.0
            while screen_y(i, hi) > top - step_px and hi < 1e4:
                hi *= 2.0
            for _ in range(50):  # the anchor rises monotonically with the height
                mid = 0.5 * (lo + hi)
                lo, hi = (lo, mid) if screen_y(i, mid) <= top - step_px else (mid, hi)
            heights[i] = hi
        top = min(top, screen_y(i, heights[i]))
    return heights


def pole_heights(track: Track, start: FloatArray, car: CarParams | None = None) -> FloatArray:
    """Heights (n,) m of the cars' label poles in the default view (:func:`fit_view`).

    The lowest label floats 1.2 marker lengths above its car; the others are stacked
    :data:`LABEL_STEP_PX` apart on the screen by :func:`label_heights` at the ``start`` poses.
    """
    base = 1.2 * marker_length(track, car or CarParams())
    return label_heights(fit_view(track), start, LABEL_STEP_PX, base)


class SceneCars:
    """The cars of a scene built by :func:`build_scene`: move them and update their labels.

    Attributes:
        nodes: one frame node per car (its pose moves the body, marker, pole and label).
        labels: one label per car (``P<position> <name>``).
        board: the standings label (every car's position and lap), beside the track.
    """

    def __init__(self, nodes: list[Any], labels: list[Any], board: Any, names: list[str]) -> None:
        self.nodes = nodes
        self.labels = labels
        self.board = board
        self.names = names
        self.shown = [False] * len(nodes)
        self.texts = [str(label.text) for label in labels]
        self.board_text = str(board.text)

    def move(self, poses: FloatArray) -> None:
        """Set each car to its pose (n, 3) [x m, y m, yaw rad]; a NaN row hides the car."""
        move_cars(self.nodes, poses, self.shown)

    def rank(self, standing: Standing, laps: int, t: float | None = None) -> None:
        """Show ``standing`` on the car labels and the board (only what changed is sent)."""
        for c, label in enumerate(self.labels):
            text = f"P{standing.position(c)} {self.names[c]}"
            if text != self.texts[c]:
                label.text = text
                self.texts[c] = text
        leader = standing.order[0] if standing.order else 0
        lap = min(standing.laps[leader] + 1, laps) if laps > 0 else standing.laps[leader] + 1
        head = f"Lap {lap}/{laps}" if laps > 0 else f"Lap {lap}"
        if standing.order and standing.finished[leader]:
            head = "Finished"
        board = f"{head}\n{standings_text(standing, self.names, laps)}"
        if board != self.board_text:
            self.board.text = board
            self.board_text = board


def replay_car(size: dict[str, Any]) -> CarParams:
    """The car dimensions of a replay log's ``car`` entry (the default car for old logs).

    >>> replay_car({"name": "deepracer", "length": 0.26, "width": 0.19, "height": 0.1}).length
    0.26
    >>> replay_car({}) == CarParams()
    True
    """
    dims = {k: float(size[k]) for k in ("length", "width", "height") if k in size}
    return dataclasses.replace(CarParams(), **dims)


def build_scene(
    server: Any,
    track: Track,
    cars: list[dict[str, Any]],
    car: CarParams | None = None,
    start: FloatArray | None = None,
) -> SceneCars:
    """Add the static scene and one (hidden) node per car to a viser server.

    Args:
        server: a ``viser.ViserServer``.
        track: the race's track.
        cars: per car ``{"agent", "name", "colour": [r, g, b]}`` (a replay log's ``cars``).
        car: the car's dimensions (default :class:`~arena.sim.CarParams`).
        start: the cars' first poses (n, 3), so that their labels do not overlap there.

    Returns:
        The cars, to move and rank frame by frame.
    """
    car = car or CarParams()
    scene = server.scene
    scene.set_up_direction("+z")
    view = fit_view(track)
    xmin, ymin, xmax, ymax = track.bounds
    cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    scene.add_grid(
        "/ground",
        width=xmax - xmin + 4.0,
        height=ymax - ymin + 4.0,
        cell_size=1.0,
        section_size=5.0,
        plane="xy",
        position=(cx, cy, -0.01),
    )
    verts, faces = track_ribbon(track)
    scene.add_mesh_simple(
        "/track/surface", verts, faces, color=ROAD_COLOUR, side="double", cast_shadow=False
    )
    for name, border in (("left", track.left_border), ("right", track.right_border)):
        seg, cols = kerb_segments(border)
        scene.add_line_segments(f"/track/kerb_{name}", seg, cols, thickness=KERB_WIDTH)
    gate = track.gates([0.0])[0]
    line = np.concatenate([gate, np.full((2, 1), LINE_Z)], axis=1)[None].astype(np.float32)
    scene.add_line_segments("/track/start_finish", line, (255, 255, 255), thickness=0.1)
    marker = marker_length(track, car)
    arrow_verts, arrow_faces = _arrow(marker)
    first = np.full((len(cars), 3), np.nan) if start is None else np.asarray(start, np.float64)
    heights = pole_heights(track, first, car)
    names = [
        str(info.get("name", info.get("agent", f"car_{i}")))[:20] for i, info in enumerate(cars)
    ]
    nodes, labels = [], []
    for i, info in enumerate(cars):
        colour = tuple(int(c) for c in info.get("colour", (200, 200, 200)))
        node = scene.add_frame(f"/cars/car_{i}", show_axes=False, visible=False)
        scene.add_box(
            f"/cars/car_{i}/body",
            color=colour,
            dimensions=(car.length, car.width, car.height),
            position=(0.0, 0.0, 0.5 * car.height),
        )
        scene.add_box(  # a dark nose, so the heading reads at a glance
            f"/cars/car_{i}/nose",
            color=(25, 25, 25),
            dimensions=(0.15 * car.length, 0.8 * car.width, 0.3 * car.height),
            position=(0.45 * car.length, 0.0, car.height),
        )
        scene.add_mesh_simple(  # visible from the whole-track view
            f"/cars/car_{i}/marker",
            arrow_verts,
            arrow_faces,
            color=colour,
            position=(0.0, 0.0, 1.5 * car.height),
            cast_shadow=False,
        )
        pole = float(heights[i])
        scene.add_box(  # a pole in the car's colour up to its label: which label is whose
            f"/cars/car_{i}/pole",
            color=colour,
            dimensions=(0.05 * marker, 0.05 * marker, pole),
            position=(0.0, 0.0, 0.5 * pole),
            cast_shadow=False,
        )
        labels.append(
            scene.add_label(
                f"/cars/car_{i}/label",
                f"P{i + 1} {names[i]}",
                position=(0.0, 0.0, pole),
                anchor="bottom-left",
            )
        )
        nodes.append(node)
    board = scene.add_label(  # the standings, at the track's far left corner
        "/standings",
        "Lap 1",
        position=_board_corner(track, view),
        anchor="top-left",
    )
    server.initial_camera.fov = view.fov
    server.initial_camera.position = view.position
    server.initial_camera.look_at = view.look_at
    return SceneCars(nodes, labels, board, names)


def _board_corner(track: Track, view: View) -> tuple[float, float, float]:
    """The corner of the track's bounds drawn top-left in ``view`` (where the board goes)."""
    xmin, ymin, xmax, ymax = track.bounds
    corners = np.array([[xmin, ymin], [xmin, ymax], [xmax, ymin], [xmax, ymax]])
    pos = np.asarray(view.position)
    forward = np.asarray(view.look_at) - pos
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = np.column_stack([corners, np.zeros(4)]) - pos
    depth = rel @ forward
    score = (rel @ up) / depth - (rel @ right) / depth  # high and to the left
    x, y = corners[int(np.argmax(score))]
    return (float(x), float(y), 0.0)


def move_cars(nodes: list[Any], poses: FloatArray, shown: list[bool]) -> None:
    """Set each car node to its pose (n, 3) [x m, y m, yaw rad]; NaN hides it.

    ``shown`` (n,) holds each node's visibility and is updated (viser sends only changes).
    """
    poses = np.asarray(poses, dtype=np.float64)
    present = ~np.isnan(poses[:, 0])
    wxyz = yaw_to_wxyz(np.nan_to_num(poses[:, 2]))
    for c, node in enumerate(nodes):
        if present[c]:
            node.position = (float(poses[c, 0]), float(poses[c, 1]), 0.0)
            node.wxyz = wxyz[c]
        if bool(present[c]) != shown[c]:
            node.visible = bool(present[c])
            shown[c] = bool(present[c])


def chase_camera(pose: FloatArray, distance: float) -> tuple[FloatArray, FloatArray]:
    """A camera behind and above a car at ``pose`` (3,): ``(position, look_at)`` (3,) m each."""
    x, y, yaw = (float(v) for v in pose[:3])
    back = np.array([np.cos(yaw), np.sin(yaw)])
    position = np.array([x - distance * back[0], y - distance * back[1], 0.6 * distance])
    return position, np.array([x, y, 0.0])


class LiveScene:
    """A viser server showing a race as it happens (or a replay as it plays).

    Its GUI panel shows the race clock, the standings (positions and laps) and a **Follow**
    dropdown: choosing a car makes every connected browser's camera chase it.

    Args:
        track: the race's track.
        cars: per car ``{"agent", "name", "colour"}``.
        host: address to listen on.
        port: port to listen on (0: any free one).
        laps: the race's lap count (0: unknown).
        start: the cars' first poses (n, 3), to place their labels apart.
    """

    def __init__(
        self,
        track: Track,
        cars: list[dict[str, Any]],
        host: str = "127.0.0.1",
        port: int = 8080,
        laps: int = 0,
        start: FloatArray | None = None,
        car: CarParams | None = None,
    ) -> None:
        import viser  # noqa: PLC0415 - optional `eval` extra

        quiet = io.StringIO()
        with contextlib.redirect_stdout(quiet):  # viser prints its address table
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        car = car or CarParams()
        self.cars = build_scene(self.server, track, cars, car=car, start=start)
        self.laps = laps
        self.tracker = StandingsTracker(track, [str(c.get("agent", "")) for c in cars])
        self.chase = 6.0 * marker_length(track, car)
        self.status = self.server.gui.add_markdown("**t = 0.0 s**")
        self.follow = self.server.gui.add_dropdown(
            "Follow", ("whole track", *self.cars.names), initial_value="whole track"
        )
        self.follow.on_update(lambda _: self._refocus())
        self.poses = np.full((len(cars), 3), np.nan)

    @property
    def nodes(self) -> list[Any]:
        """The car nodes (one per car)."""
        return self.cars.nodes

    @property
    def shown(self) -> list[bool]:
        """Per car, whether it is shown."""
        return self.cars.shown

    @property
    def url(self) -> str:
        """Where to open the scene in a browser."""
        return f"http://{self.server.get_host()}:{self.server.get_port()}/"

    def followed(self) -> int | None:
        """The index of the car the cameras chase, or None (the whole-track view)."""
        names = self.cars.names
        value = str(self.follow.value)
        return names.index(value) if value in names else None

    def _refocus(self) -> None:
        """Point every browser's camera at the followed car (or back at the whole track)."""
        car = self.followed()
        for client in self.server.get_clients().values():
            if car is None:
                view = fit_view(self.tracker.track)
                client.camera.position = view.position
                client.camera.look_at = view.look_at
            elif not np.isnan(self.poses[car, 0]):
                position, look_at = chase_camera(self.poses[car], self.chase)
                client.camera.position = position
                client.camera.look_at = look_at

    def show(self, t: float, poses: FloatArray, events: Sequence[dict[str, Any]] = ()) -> None:
        """Move the cars to ``poses`` (n, 3) at race time ``t`` s; ``events``: new ones."""
        self.poses = np.asarray(poses, dtype=np.float64)
        for e in events:
            self.tracker.event(e)
        standing = self.tracker.frame(t, self.poses)
        with self.server.atomic():
            self.cars.move(self.poses)
            self.cars.rank(standing, self.laps)
        text = standings_text(standing, self.cars.names, self.laps).replace("\n", "  \n")
        self.status.content = f"**t = {t:.1f} s**  \n{text}"
        if self.followed() is not None:
            self._refocus()

    def close(self) -> None:
        """Stop the server."""
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


class LiveWatcher:
    """Shows each new frame of a replay log in a :class:`LiveScene`, paced to race time.

    Use as the callback of :func:`arena.replay.observe` (``slipstream race --watch``) or call
    :meth:`play` on a finished log (``slipstream replay``).

    Args:
        scene: where to draw.
        speed: race seconds per wall-clock second (1: real time; 0: as fast as it comes).
    """

    def __init__(self, scene: LiveScene, speed: float = 1.0) -> None:
        self.scene = scene
        self.speed = speed
        self.start: float | None = None
        self.seen = 0  # events of the log already passed on

    def frame(
        self, t: float, row: list[list[float] | None], events: Sequence[dict[str, Any]] = ()
    ) -> None:
        """Draw one frame: race time ``t`` s, one pose (or None) per car, new events."""
        now = time.monotonic()
        if self.start is None:
            self.start = now - (t / self.speed if self.speed > 0 else 0.0)
        if self.speed > 0:
            wait = self.start + t / self.speed - now
            if wait > 0:
                time.sleep(wait)
        nan = [float("nan")] * 3
        poses = np.array([p if p is not None else nan for p in row], dtype=np.float64)
        self.scene.show(t, poses, events)

    def __call__(self, log: Any) -> None:
        """The :func:`arena.replay.observe` callback: draw the log's newest frame."""
        new = log.events[self.seen :]
        self.seen = len(log.events)
        self.frame(float(log.t[-1]), log.poses[-1], new)

    def play(self, log: Any) -> None:
        """Play a whole replay log once (events at their times)."""
        self.start = None
        self.scene.laps = race_laps(log.events, getattr(log, "laps", 0))
        self.scene.tracker = StandingsTracker(
            self.scene.tracker.track, [str(c.get("agent", "")) for c in log.cars]
        )
        events = sorted(log.events, key=lambda e: float(e.get("t", 0.0)))
        k = 0
        for t, row in zip(log.t, log.poses, strict=True):
            j = k
            while j < len(events) and float(events[j].get("t", 0.0)) <= t:
                j += 1
            self.frame(float(t), row, events[k:j])
            k = j


__all__ = [
    "LiveScene",
    "LiveWatcher",
    "SceneCars",
    "View",
    "build_scene",
    "chase_camera",
    "fit_view",
    "kerb_segments",
    "label_heights",
    "marker_length",
    "move_cars",
    "pole_heights",
    "project",
    "replay_car",
    "track_ribbon",
    "yaw_to_wxyz",
]
