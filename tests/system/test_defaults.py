"""The built-in configs shipped in the package: each one loads, and deploy/ holds the same settings (its copies are
the ones to edit for a deployment)."""

from __future__ import annotations

from pathlib import Path

import json5
import pytest

from occvo_services import defaults
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import router_endpoint
from occvo_services.supervisor import UpConfig

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


# acl_router.json5 is the logins' ACL template, not a config of its own: tests/service/test_logins.py checks its rules
@pytest.mark.parametrize("name", [n for n in defaults.NAMES if n != "acl_router.json5"])
def test_built_in_config_loads_and_matches_its_deploy_copy(name):
    path = defaults.path(name)
    assert path.is_file()
    if name == "occvo.json5":
        up = UpConfig.load(path)
        assert {w.role for w in up.workers} == {"inference", "registration", "map"}
        assert up.endpoint() == router_endpoint(defaults.path("router.json5"))
    elif name == "router.json5":
        assert router_endpoint(path) == "tcp/127.0.0.1:7447"
    else:
        WorkerConfig.load(path)
    assert json5.loads(path.read_text()) == json5.loads((DEPLOY / name).read_text())


def test_unknown_built_in_config_is_refused():
    with pytest.raises(KeyError, match="no built-in config"):
        defaults.path("nope.json5")
