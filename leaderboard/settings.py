"""Settings of the leaderboard service, read from the environment by pydantic-settings.

Every field can be set with an environment variable prefixed ``SLIPSTREAM_`` (for example
``SLIPSTREAM_DATABASE_URL=postgresql+psycopg://user@host/db``) or passed to
``Settings(...)`` directly; tests build one per temporary database. Nothing here is read at
import time: :func:`leaderboard.app.create_app` takes a ``Settings`` object.

Files the service keeps under ``data_dir``::

    data_dir/leaderboard.db                     SQLite database (when database_url is unset)
    data_dir/bundles/<submission>/v<n>-<r>.zip  every uploaded bundle version, as uploaded
                                                (<r>: random, so concurrent uploads never clash)
    data_dir/replays/<race_id>.viser            3D replay (served at /replays/<race_id>.viser)
    data_dir/replays/<race_id>.replay.json.gz   raw replay log (to regenerate the .viser files)
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# Placeholder secrets that people copy from examples; refused so a deployment cannot run with one.
_DEFAULT_SECRETS = frozenset({"changethis", "changeme", "secret", "admin", "password", ""})


class Settings(BaseSettings):
    """Configuration of one leaderboard deployment (web process and workers alike)."""

    model_config = SettingsConfigDict(env_prefix="SLIPSTREAM_", extra="ignore")

    data_dir: Path = Field(
        default=Path("artifacts/leaderboard"),
        description="folder for the SQLite database, uploaded bundles and replays",
    )
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL; default: SQLite (WAL) at data_dir/leaderboard.db",
    )
    admin_token: SecretStr | None = Field(
        default=None,
        description="bearer token allowed to create users over the API (unset: CLI only)",
    )
    max_upload_mb: float = Field(default=64.0, gt=0, description="largest bundle accepted, MiB")
    max_versions: int = Field(default=50, ge=1, description="versions kept per submission")
    auto_migrate: bool = Field(default=True, description="run `alembic upgrade head` on start")
    lease_s: float = Field(default=120.0, gt=0, description="a worker's lease on a race, s")
    max_attempts: int = Field(default=3, ge=1, description="runs of a race before it fails")
    race_laps: int = Field(default=2, ge=1, description="laps per ranked race")
    validation_track: str = Field(default="oval", description="track of validation races")
    validation_opponent: str = Field(
        default="pursuit", description="baseline that a new version races in its validation"
    )
    tracks: list[str] | None = Field(
        default=None, description="tracks for ranked races (default: the built-in library)"
    )
    min_cars: int = Field(default=2, ge=2, le=8, description="fewest cars in a ranked race")
    max_cars: int = Field(default=4, ge=2, le=8, description="most cars in a ranked race")
    robustness: bool = Field(
        default=True,
        description="workers queue a robustness run (leaderboard.robustness) per ranked version",
    )
    page_size: int = Field(default=50, ge=1, le=500, description="default rows per page")
    provisional_races: int = Field(
        default=5,
        ge=0,
        description="rated races before a submission leaves the provisional part of the table",
    )
    # ---- front door (see leaderboard.limits and leaderboard.security) ----
    allowed_hosts: list[str] = Field(
        default=["127.0.0.1", "localhost"],
        description="Host header values served (TrustedHostMiddleware; '*' allows any)",
    )
    max_request_kb: float = Field(
        default=64.0, gt=0, description="largest request body outside uploads, KiB"
    )
    body_idle_timeout_s: float = Field(
        default=15.0,
        gt=0,
        description="longest wait for the next piece of a request body, and for the whole "
        "body of a request that is not an upload, s",
    )
    upload_timeout_s: float = Field(
        default=300.0, gt=0, description="longest time to receive a whole upload body, s"
    )
    header_timeout_s: float = Field(
        default=10.0,
        gt=0,
        description="longest time from a connection (or its previous answer) to a complete "
        "request head, s (slowloris)",
    )
    max_concurrent_uploads: int = Field(
        default=8, ge=1, description="uploads per user being received at once (429 beyond)"
    )
    keep_alive_s: float = Field(
        default=5.0, gt=0, description="idle keep-alive connections are closed after this, s"
    )
    max_connections: int = Field(
        default=256, ge=1, description="concurrent connections before uvicorn answers 503"
    )
    web_workers: int | None = Field(
        default=None,
        ge=1,
        description="processes serving the app: `slipstream serve`'s default (unset: 1), "
        "and the count in-memory rate limits are divided by (unset: 1; set it to N under "
        "`uvicorn --workers N`)",
    )
    rate_limits: bool = Field(default=True, description="enforce the rate limits below")
    rate_limit_ip: str = Field(default="600/minute", description="requests per client address")
    rate_limit_token: str = Field(default="300/minute", description="requests per API token")
    rate_limit_auth_failures: str = Field(
        default="20/minute", description="401 answers per client address before 429s"
    )
    rate_limit_storage: str = Field(
        default="memory://", description="counter storage of the `limits` library (redis://...)"
    )
    max_uploads_per_day: int = Field(
        default=20, ge=1, description="bundle uploads per user in any 24 hours"
    )
    max_active_submissions: int = Field(
        default=10, ge=1, description="submissions per user that are pending or active"
    )
    random_track_images: int = Field(
        default=64, ge=1, description="plots of generated (random:) tracks kept on disk"
    )
    cache_max_age_s: float = Field(
        default=30.0, ge=0, description="longest a cached leaderboard/track snapshot is kept, s"
    )

    @field_validator("admin_token")
    @classmethod
    def _refuse_default_secret(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and value.get_secret_value().strip().lower() in _DEFAULT_SECRETS:
            raise ValueError("admin_token is a well-known placeholder; set a random secret")
        if value is not None and len(value.get_secret_value()) < 16:
            raise ValueError("admin_token must be at least 16 characters")
        return value

    @field_validator("rate_limit_ip", "rate_limit_token", "rate_limit_auth_failures")
    @classmethod
    def _valid_rate(cls, value: str) -> str:
        import limits  # noqa: PLC0415 - only to check the syntax

        limits.parse(value)  # ValueError names the bad rate
        return value

    @property
    def db_url(self) -> str:
        """The database URL in use (SQLite under ``data_dir`` unless ``database_url`` is set)."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'leaderboard.db').resolve()}"

    @property
    def replays_dir(self) -> Path:
        """Folder of ``<race_id>.viser`` and ``<race_id>.replay.json.gz`` files."""
        return self.data_dir / "replays"

    @property
    def bundles_dir(self) -> Path:
        """Folder of uploaded bundles, one sub-folder per submission."""
        return self.data_dir / "bundles"

    @property
    def max_upload_bytes(self) -> int:
        """``max_upload_mb`` in bytes."""
        return int(self.max_upload_mb * 1024 * 1024)

    def ensure_dirs(self) -> None:
        """Create the data, bundle and replay folders if missing."""
        for folder in (self.data_dir, self.replays_dir, self.bundles_dir):
            folder.mkdir(parents=True, exist_ok=True)
