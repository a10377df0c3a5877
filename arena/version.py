"""The env's version, importable without pybullet (the leaderboard's web process reads it).

``ENV_VERSION`` changes whenever the env's behaviour changes (see the Version History in
:class:`arena.env.RacingEnv`). ``COMPATIBLE_ENV_VERSIONS`` lists the versions whose
observations, actions and rewards mean the same as this one's, so a policy trained on any of
them drives this env unchanged (0.2 only added options: uncertainty sets and nature agents;
0.3 made one episode core for both backends and added ``state()``, ``park_finished`` and car
presets, with observations, actions and rewards unchanged).
"""

ENV_VERSION = "0.3"
COMPATIBLE_ENV_VERSIONS: tuple[str, ...] = ("0.1", "0.2", "0.3")


def is_compatible(version: str) -> bool:
    """Whether a policy made for env ``version`` runs on this env unchanged.

    >>> is_compatible("0.1"), is_compatible("9.9")
    (True, False)
    """
    return version in COMPATIBLE_ENV_VERSIONS
