"""The leaderboard service, and the ``slipstream`` command line that sits on top of every package.

Nothing here imports pybullet or torch at import time: the web process only stores and serves
what the evaluation workers produce.
"""
