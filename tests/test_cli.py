from __future__ import annotations

from pathlib import Path

from grpc_health.v1 import health_pb2

from services.control.server import ControlService
from user.cli import main
from user.config import AuthConfig, StackConfig


def test_health_probe_needs_no_token(monkeypatch, capsys):
    cfg = StackConfig(auth=AuthConfig(token="server-secret"))
    cfg.control.server.port = 0
    service = ControlService(cfg, start_metrics=False).start()
    address = service.address
    try:
        monkeypatch.delenv("USER_TOKEN", raising=False)
        assert main(["health", address]) == 0
        assert capsys.readouterr().out == f"{address}: SERVING\n"
        service.running.health.set("", health_pb2.HealthCheckResponse.NOT_SERVING)
        assert main(["health", address]) == 1
        assert capsys.readouterr().out == f"{address}: NOT_SERVING\n"
    finally:
        service.stop()
    assert main(["health", address, "--timeout", "0.5"]) == 1
    out = capsys.readouterr().out
    assert out.startswith(f"{address}: unreachable (UNAVAILABLE") and out.count("\n") == 1, out


def test_ops_commands_without_a_token_say_so_in_one_line(tmp_path: Path, monkeypatch, capsys):
    monkeypatch.delenv("USER_TOKEN", raising=False)
    for argv in (["robots", "ls"], ["exp", "ls"], ["workers", "ls"], ["command", "pause"]):
        assert main([*argv, "--set", f"up.runs_dir={tmp_path}"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"userctl {argv[0]}: auth.token: auth is enabled but no token is set"), err
        assert err.count("\n") == 1
