"""The cars' colours, shared by the camera, the top-down render, replays and the website.

Importable without pybullet (the leaderboard's web process colours its charts with it).
"""

CAR_RGB: tuple[tuple[int, int, int], ...] = (  # car i's colour everywhere
    (230, 57, 70),
    (29, 120, 214),
    (255, 183, 3),
    (42, 157, 143),
    (155, 93, 229),
    (244, 132, 95),
    (6, 214, 160),
    (239, 71, 111),
)


def car_colour(i: int) -> tuple[int, int, int]:
    """RGB colour of car ``i`` (shared by the camera, the top-down render and replays)."""
    return CAR_RGB[i % len(CAR_RGB)]
