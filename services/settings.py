"""Service settings, from ``KNEEMESH_*`` environment variables (the CLI flags set the same names)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from kneemesh_core.errors import KneeMeshError

GiB = 1 << 30


def _api_keys(text: str) -> dict[str, str]:
    """``"alice:KEY1,bob:KEY2"`` (or bare ``"KEY1,KEY2"``) -> {key: owner name}."""
    keys: dict[str, str] = {}
    for i, item in enumerate(filter(None, (x.strip() for x in text.split(",")))):
        name, _, key = item.rpartition(":")
        if len(key) < 8:
            raise KneeMeshError("bad_option", f"KNEEMESH_API_KEYS: key {i + 1} is shorter than 8 characters.")
        keys[key] = name or f"key{i + 1}"
    return keys


@dataclasses.dataclass(frozen=True)
class Settings:
    """Everything the API and the workers need to agree on.

    ``broker_url`` None means embedded mode: the API runs jobs on an in-process pool.
    ``api_keys`` empty means no authentication (one machine, one lab); otherwise every
    request needs ``X-API-Key`` and a key sees only its own jobs.
    """

    data_dir: Path = Path("kneemesh-data")
    broker_url: str | None = None
    result_backend: str | None = None
    api_keys: dict[str, str] = dataclasses.field(default_factory=dict)
    max_upload_bytes: int = 1 * GiB
    workers: int = 2
    task_soft_time_limit_s: int = 1500
    task_time_limit_s: int = 1800
    # Must exceed the longest task: Redis redelivers unacknowledged tasks after it.
    visibility_timeout_s: int = 7200
    retention_days: float = 30.0

    @classmethod
    def from_env(cls, **overrides) -> "Settings":
        env = os.environ
        s = cls(
            data_dir=Path(env.get("KNEEMESH_DATA_DIR", "kneemesh-data")),
            broker_url=env.get("KNEEMESH_BROKER_URL") or None,
            result_backend=env.get("KNEEMESH_RESULT_BACKEND") or None,
            api_keys=_api_keys(env.get("KNEEMESH_API_KEYS", "")),
            max_upload_bytes=int(env.get("KNEEMESH_MAX_UPLOAD_BYTES", GiB)),
            workers=int(env.get("KNEEMESH_WORKERS", 2)),
            task_soft_time_limit_s=int(env.get("KNEEMESH_TASK_SOFT_TIME_LIMIT", 1500)),
            task_time_limit_s=int(env.get("KNEEMESH_TASK_TIME_LIMIT", 1800)),
            visibility_timeout_s=int(env.get("KNEEMESH_VISIBILITY_TIMEOUT", 7200)),
            retention_days=float(env.get("KNEEMESH_RETENTION_DAYS", 30)),
        )
        return dataclasses.replace(s, **{k: v for k, v in overrides.items() if v is not None})

    @property
    def backend_url(self) -> str | None:
        """Celery's result backend: the broker's Redis unless set apart."""
        return self.result_backend or self.broker_url
