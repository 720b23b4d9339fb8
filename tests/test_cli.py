from __future__ import annotations

from services.control.server import ControlService
from user.cli import main
from user.config import AuthConfig, StackConfig


def test_health_probe_needs_no_token(monkeypatch):
    cfg = StackConfig(auth=AuthConfig(token="server-secret"))
    cfg.control.server.port = 0
    service = ControlService(cfg, start_metrics=False).start()
    address = service.address
    try:
        monkeypatch.delenv("USER_TOKEN", raising=False)
        assert main(["health", address]) == 0
    finally:
        service.stop()
    assert main(["health", address, "--timeout", "0.5"]) == 1
