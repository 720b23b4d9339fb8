"""Start-up failures are one line naming the setting or file, exit 2: busy gRPC and metrics ports of every
service command, bad TLS files (checked before binding), and bad `userctl health` targets.

Real servers and held sockets on 127.0.0.1 with ephemeral ports; the CLI runs as a subprocess where its
exit code and stderr are the point.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from services.control.server import ControlService
from tests.test_auth import ADMIN, make_pki
from user import arg_types, cli, rpc
from user.config import AuthConfig, ConfigError, StackConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def busy_port() -> Iterator[int]:
    """A port another process would hold: bound and listening on 127.0.0.1 for the whole test."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        yield holder.getsockname()[1]


def stack_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "stack.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "log_level": "WARNING",
                "auth": {"token": ADMIN},
                "replay": {"path": str(tmp_path / "replay"), "map_size_mb": 64},
            }
        )
    )
    return path


def userctl(tmp_path: Path, *argv: str) -> tuple[int, list[str]]:
    """Run `userctl ARGV` in tmp_path (the edge's spool goes there); exit code and the stderr lines that are
    not JSON log records."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("USER__") and k != "USER_TOKEN"}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run(
        [sys.executable, "-m", "user.cli", *argv], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc.returncode, [line for line in proc.stderr.splitlines() if not line.startswith("{")]


# --------------------------------------------------------------------------- busy ports


@pytest.mark.parametrize(
    ("command", "field"),
    [
        ("control", "port"),
        ("control", "metrics_port"),
        ("replay", "port"),
        ("replay", "metrics_port"),
        ("inference", "port"),
        ("inference", "metrics_port"),
        ("learner", "port"),
        ("learner", "metrics_port"),
    ],
)
def test_a_busy_port_names_the_service_setting(tmp_path: Path, busy_port: int, command: str, field: str) -> None:
    other = "metrics_port" if field == "port" else "port"
    config = str(stack_yaml(tmp_path))
    sets = ["--set", f"{command}.server.{field}={busy_port}", "--set", f"{command}.server.{other}=0"]
    code, lines = userctl(tmp_path, command, "-c", config, *sets)
    # Exactly our line: no traceback, and no gRPC C-core log line about the failed bind either.
    assert (code, lines) == (2, [f"userctl {command}: {command}.server.{field} {busy_port} is in use on 127.0.0.1"])


def test_a_busy_edge_metrics_port_is_one_line(tmp_path: Path, busy_port: int) -> None:
    code, lines = userctl(tmp_path, "edge", "-c", str(stack_yaml(tmp_path)), "--set", f"edge.metrics_port={busy_port}")
    assert (code, lines) == (2, [f"userctl edge: edge.metrics_port {busy_port} is in use on 127.0.0.1"])


def unused_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bindable(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def test_a_busy_metrics_port_leaves_no_grpc_port_bound(busy_port: int) -> None:
    """The gRPC port is not held by the failed start: the service starts on it right after."""
    cfg = StackConfig(auth=AuthConfig(token=ADMIN))
    cfg.control.server.port, cfg.control.server.metrics_port = unused_port(), busy_port
    with pytest.raises(ConfigError, match=rf"^control\.server\.metrics_port {busy_port} is in use"):
        ControlService(cfg).start()
    assert bindable(cfg.control.server.port)
    cfg.control.server.metrics_port = 0
    service = ControlService(cfg).start()
    try:
        assert service.port == cfg.control.server.port
    finally:
        service.stop()


def test_a_host_that_is_not_here_names_the_host_setting() -> None:
    cfg = StackConfig(auth=AuthConfig(token=ADMIN))
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.host = "host.invalid"  # .invalid never resolves (RFC 2606)
    with pytest.raises(ConfigError, match=r"^control\.server\.host 'host\.invalid' is not a known host"):
        ControlService(cfg, start_metrics=False).start()


# --------------------------------------------------------------------------- TLS files


def tls_cfg(**auth: object) -> StackConfig:
    cfg = StackConfig(auth=AuthConfig(token=ADMIN, **auth))
    cfg.control.server.port = 0
    return cfg


@pytest.fixture
def pki(tmp_path: Path) -> dict[str, Path]:
    paths = make_pki(tmp_path)
    (tmp_path / "other").mkdir()
    paths["other_key"] = make_pki(tmp_path / "other")["server_key"]
    paths["not_pem"] = tmp_path / "stack.yaml"
    paths["not_pem"].write_text("log_level: INFO\n")
    paths["missing"] = tmp_path / "missing.pem"
    paths["dir"] = tmp_path
    return paths


@pytest.mark.parametrize(
    ("auth", "said"),
    [
        ({"tls_cert": "server"}, r"^auth\.tls_key is required with auth\.tls_cert$"),
        ({"tls_key": "server_key"}, r"^auth\.tls_key is set but auth\.tls_cert is not"),
        ({"tls_cert": "ca", "tls_key": "server_key", "tls_client_ca": "ca"}, r"^auth\.tls_key .* does not match"),
        ({"tls_client_ca": "ca"}, r"^auth\.tls_client_ca is set but auth\.tls_cert is not"),
        ({"tls_cert": "not_pem", "tls_key": "server_key"}, r"^auth\.tls_cert .*stack\.yaml: not a PEM certificate"),
        ({"tls_cert": "missing", "tls_key": "server_key"}, r"^auth\.tls_cert .*missing\.pem: cannot read it \(No such"),
        ({"tls_cert": "dir", "tls_key": "server_key"}, r"^auth\.tls_cert .*: cannot read it \(Is a directory\)"),
        ({"tls_cert": "server", "tls_key": "server"}, r"^auth\.tls_key .*server\.pem: not a PEM private key"),
        ({"tls_cert": "server", "tls_key": "missing"}, r"^auth\.tls_key .*missing\.pem: cannot read it"),
        ({"tls_cert": "server", "tls_key": "other_key"}, r"^auth\.tls_key .*other.server_key\.pem does not match"),
        ({"tls_cert": "server", "tls_key": "server_key", "tls_client_ca": "not_pem"}, r"^auth\.tls_client_ca .*"),
    ],
)
def test_a_bad_tls_setting_names_the_field_and_file(pki: dict[str, Path], auth: dict[str, str], said: str) -> None:
    cfg = tls_cfg(**{field: pki[label] for field, label in auth.items()})
    with pytest.raises(ConfigError, match=said):
        ControlService(cfg, start_metrics=False).start()


def test_an_encrypted_key_is_named(pki: dict[str, Path], tmp_path: Path) -> None:
    from cryptography.hazmat.primitives import serialization

    key = serialization.load_pem_private_key(pki["server_key"].read_bytes(), password=None)
    locked = tmp_path / "locked.pem"
    locked.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.BestAvailableEncryption(b"passphrase"),
        )
    )
    with pytest.raises(ConfigError, match=r"^auth\.tls_key .*locked\.pem: the private key is encrypted"):
        ControlService(tls_cfg(tls_cert=pki["server"], tls_key=locked), start_metrics=False).start()


def test_without_cryptography_the_pem_markers_still_name_the_file(
    pki: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`cryptography` is a dev dependency: without it the PEM markers are checked, and a marked but broken
    certificate that gRPC refuses is still reported as a TLS problem, not as a port in use."""
    monkeypatch.setitem(sys.modules, "cryptography", None)  # any import of it now fails
    with pytest.raises(ConfigError, match=r"^auth\.tls_cert .*stack\.yaml: not a PEM certificate"):
        ControlService(tls_cfg(tls_cert=pki["not_pem"], tls_key=pki["server_key"]), start_metrics=False).start()
    with pytest.raises(ConfigError, match=r"^auth\.tls_key .*stack\.yaml: not a PEM private key"):
        ControlService(tls_cfg(tls_cert=pki["server"], tls_key=pki["not_pem"]), start_metrics=False).start()
    broken = tmp_path / "broken.pem"
    broken.write_text("-----BEGIN CERTIFICATE-----\nbm90IGEgY2VydA==\n-----END CERTIFICATE-----\n")
    cfg = tls_cfg(tls_cert=broken, tls_key=pki["server_key"])
    cfg.control.server.metrics_port = unused_port()
    with pytest.raises(ConfigError, match=r"^control: gRPC could not serve TLS with auth\.tls_cert .*broken\.pem"):
        ControlService(cfg).start()
    assert bindable(cfg.control.server.metrics_port)  # the metrics server started first was shut down


def test_userctl_reports_a_certificate_that_is_not_pem_in_one_line(tmp_path: Path) -> None:
    """The tester's repro: the YAML itself as cert and key used to read as `Failed to bind to address`."""
    config = str(stack_yaml(tmp_path))
    sets = [f"auth.tls_cert={config}", f"auth.tls_key={config}", "control.server.port=0"]
    code, lines = userctl(tmp_path, "control", "-c", config, *(a for s in sets for a in ("--set", s)))
    assert (code, lines) == (
        2,
        [f"userctl control: auth.tls_cert {config}: not a PEM certificate (no BEGIN CERTIFICATE block)"],
    )


def test_a_certificate_without_its_key_exits_2(tmp_path: Path) -> None:
    config = str(stack_yaml(tmp_path))
    code, lines = userctl(tmp_path, "control", "-c", config, "--set", "auth.tls_cert=/tmp/nope.pem")
    assert (code, lines) == (2, ["userctl control: auth.tls_key is required with auth.tls_cert"])


# --------------------------------------------------------------------------- userctl health targets


@pytest.mark.parametrize(
    ("target", "said"),
    [
        ("", "'' is not HOST:PORT"),
        ("127.0.0.1", "'127.0.0.1' is not HOST:PORT"),
        ("127.0.0.1:", "has no port"),
        ("127.0.0.1:99999", "port 99999 is outside 1-65535"),
        ("127.0.0.1:0", "port 0 is outside 1-65535"),
        ("127.0.0.1:http", "port 'http' is not a number"),
        ("127.0.0.1:5e4", "port '5e4' is not a number"),
        (":50051", "is not HOST:PORT"),
        ("::1:50051", "put an IPv6 address in brackets"),
        ("[]:50051", "bad bracketed IPv6 host"),
        ("bad host:50051", "is not a host name or address"),
    ],
)
def test_health_rejects_a_bad_target_before_making_a_channel(
    target: str, said: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_channel(*_: object) -> None:
        raise AssertionError("a channel was made for a bad target")

    monkeypatch.setattr(rpc, "make_channel", no_channel)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["health", "127.0.0.1:50051", target])  # one bad target fails the whole call
    out, err = capsys.readouterr()
    assert exit_.value.code == 2 and out == ""
    assert err.splitlines()[-1].startswith("userctl health: error: argument HOST:PORT: ") and said in err, err


@pytest.mark.parametrize("target", ["127.0.0.1:1", "localhost:65535", "[::1]:50051", "dns.example:443"])
def test_host_port_accepts_the_usual_forms(target: str) -> None:
    assert arg_types.host_port(target) == target


def test_health_with_an_unreadable_ca_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "ca.pem"
    assert cli.main(["health", "127.0.0.1:1", "--set", f"auth.tls_ca={missing}"]) == 2
    assert (
        capsys.readouterr().err
        == f"userctl health: auth.tls_ca {missing}: cannot read it (No such file or directory)\n"
    )


def test_a_bad_tokens_file_is_one_line_without_the_token(tmp_path: Path) -> None:
    """The tester's repro: a short token used to be printed back (input_value='optoken')."""
    tokens = tmp_path / "tokens.yaml"
    tokens.write_text('- {token: "optoken", role: operator}\n')
    config = str(stack_yaml(tmp_path))
    sets = ["--set", f"auth.tokens_file={tokens}", "--set", "control.server.port=0"]
    code, lines = userctl(tmp_path, "control", "-c", config, *sets)
    assert (code, lines) == (
        2,
        [f"userctl control: auth.tokens_file {tokens}: entry 0: token: String should have at least 16 characters"],
    )
