"""The API keeps its contract: openapi.yaml is the app's, and schemathesis finds no server error."""

from __future__ import annotations

import tempfile

import schemathesis
from hypothesis import HealthCheck, settings

from conftest import ROOT
from services.api import create_app
from services.settings import Settings
from services.worker.embedded import EmbeddedRunner


class NoRun(EmbeddedRunner):
    """Accepts jobs without running them: the contract is about the HTTP surface, not meshing."""

    def start(self, jobs):
        self._thread = None

    def submit(self, rec):
        pass

    def ready(self):
        return {"ready": True, "runner": "test", "workers": 0, "detail": "ok"}


def test_openapi_yaml_is_the_apps():
    from services.api.openapi import openapi_yaml

    assert (ROOT / "openapi.yaml").read_text() == openapi_yaml(), "openapi.yaml is stale: run `kneemesh openapi --out openapi.yaml`"


_DATA = tempfile.TemporaryDirectory(prefix="kneemesh-contract-")
API = create_app(Settings(data_dir=_DATA.name, api_keys={"contract-test-key": "lab"}), runner=NoRun(1))
schema = schemathesis.openapi.from_asgi("/openapi.json", API)


@schema.parametrize()
@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case):
    case.headers = {**(case.headers or {}), "X-API-Key": "contract-test-key"}
    case.call_and_validate(checks=[schemathesis.checks.not_a_server_error])
