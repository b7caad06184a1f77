"""The OpenAPI document as committed in ``openapi.yaml`` (a test fails when the two differ)."""

from __future__ import annotations

import tempfile

import yaml

from services.settings import Settings


def openapi_yaml() -> str:
    from services.api.app import create_app
    from services.worker.embedded import EmbeddedRunner

    with tempfile.TemporaryDirectory() as tmp:  # the document does not depend on settings; nothing is started
        app = create_app(Settings(data_dir=tmp), runner=EmbeddedRunner(1))
        return yaml.safe_dump(app.openapi(), sort_keys=False, allow_unicode=True, width=120)
