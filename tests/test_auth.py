"""Roles per token, edge identity bound to its agent, token rotation, TLS and mTLS with certificates made here.

Real Control and Replay servers on 127.0.0.1:0; the certificates come from a throwaway CA built with
`cryptography` in tmp_path.
"""

from __future__ import annotations

import datetime
import ipaddress
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
import yaml

import user.auth
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests.helpers import wait_for
from tests.test_replay_store import make_step, spec
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.shm_files import host_id
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc

ADMIN = "admin-token-0123456789"
OPERATOR = "operator-token-0123456789"
READER = "reader-token-0123456789"
EDGE = "edge-token-lab-pc-1-0123456789"
WORKER = "worker-token-gpu-1-0123456789"


def write_tokens(path: Path, operator: str = OPERATOR) -> None:
    entries = [
        {"token": operator, "role": "operator", "name": "alice"},
        {"token": READER, "role": "reader", "name": "grafana"},
        {"token": EDGE, "role": "edge", "name": "lab-pc-1", "agent_id": "lab-pc-1", "robots": ["arm-*"]},
        {"cert_cn": "lab-pc-2", "role": "edge", "agent_id": "lab-pc-2"},
        {"token": WORKER, "role": "worker", "name": "gpu-1"},
    ]
    tmp = path.with_suffix(".tmp")
    tmp.write_text(yaml.safe_dump(entries))
    tmp.replace(path)


def server_cfg(tmp_path: Path, **auth: object) -> StackConfig:
    tokens = tmp_path / "tokens.yaml"
    if not tokens.exists():
        write_tokens(tokens)
    cfg = StackConfig(auth=AuthConfig(token=ADMIN, tokens_file=tokens, **auth))
    for section in (cfg.control, cfg.replay):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    return cfg


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[tuple[ControlService, ReplayService, Path]]:
    cfg = server_cfg(tmp_path)
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    yield control, replay, tmp_path / "tokens.yaml"
    replay.stop()
    control.stop()


def control_stub(svc: ControlService, token: str | None = None, **auth: object) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(svc.address, AuthConfig(token=token, **auth)))


def code_of(fn, *args, **kw) -> grpc.StatusCode:
    try:
        result = fn(*args, **kw)
        if hasattr(result, "__iter__") and not hasattr(result, "SerializeToString"):
            for _ in result:
                pass
    except grpc.RpcError as err:
        return err.code()
    return grpc.StatusCode.OK


def register(agent_id: str, *robot_ids: str) -> Iterator[control_pb2.EdgeMessage]:
    req = control_pb2.RegisterRequest(agent_id=agent_id, hostname="h", robots=[spec(r) for r in robot_ids])
    yield control_pb2.EdgeMessage(register=req)


def connect_code(stub: control_pb2_grpc.ControlStub, agent_id: str, *robot_ids: str) -> grpc.StatusCode:
    """Register and hang up: OK when control accepted the registration."""
    return code_of(stub.Connect, register(agent_id, *robot_ids), timeout=10)


def insert_code(svc: ReplayService, token: str, robot_id: str, index: int = 0, last: bool = False) -> grpc.StatusCode:
    stub = replay_pb2_grpc.ReplayStub(make_channel(svc.address, AuthConfig(token=token)))
    req = replay_pb2.InsertRequest(seq=0, step=make_step(robot_id, "ep", index, last=last))
    return code_of(stub.Insert, iter([req]), timeout=10)


def test_each_role_calls_only_its_methods(stack) -> None:
    control, _, _ = stack
    admin, operator, reader, edge = (control_stub(control, t) for t in (ADMIN, OPERATOR, READER, EDGE))
    cmd = control_pb2.SendCommandRequest(command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE))
    denied = grpc.StatusCode.PERMISSION_DENIED

    # Wrong or missing token: not even a read.
    assert code_of(
        control_stub(control, "nope-nope-nope-nope").ListRobots, control_pb2.ListRobotsRequest(), timeout=5
    ) == (grpc.StatusCode.UNAUTHENTICATED)
    # The edge registers only its own agent and robots, and cannot command or read the fleet.
    assert connect_code(edge, "lab-pc-1", "arm-0", "arm-1") == grpc.StatusCode.OK
    assert connect_code(edge, "lab-pc-9", "arm-0") == denied
    assert connect_code(edge, "lab-pc-1", "gripper-0") == denied
    assert code_of(edge.SendCommand, cmd, timeout=5) == denied
    assert code_of(edge.ListRobots, control_pb2.ListRobotsRequest(), timeout=5) == denied
    # Operators command and read, but do not impersonate edges.
    assert code_of(operator.SendCommand, cmd, timeout=5) == grpc.StatusCode.OK
    assert (
        code_of(operator.ListRobots, control_pb2.ListRobotsRequest(include_offline=True), timeout=5)
        == grpc.StatusCode.OK
    )
    assert connect_code(operator, "lab-pc-1", "arm-0") == denied
    # Readers read.
    robots = reader.ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=5).robots
    assert [r.spec.robot_id for r in robots] == ["arm-0", "arm-1"]
    assert code_of(reader.SendCommand, cmd, timeout=5) == denied
    assert connect_code(reader, "lab-pc-1", "arm-0") == denied
    # The shared token is every role (how services talk to each other, and how older configs work).
    assert code_of(admin.SendCommand, cmd, timeout=5) == grpc.StatusCode.OK
    assert connect_code(admin, "any-agent", "other-0") == grpc.StatusCode.OK


def test_every_role_that_reads_weights_gets_them_through_the_stream_our_subscribers_use(tmp_path: Path) -> None:
    """WeightSubscriber (a local-policy edge, an inference host) calls StreamWeights: an edge, worker or reader
    token must receive weights through it, as through SubscribeWeights."""
    import numpy as np

    from user import rpc
    from user.config import ServerConfig
    from user.v1 import learner_pb2
    from user.weights import WeightServicer, WeightStore, WeightSubscriber, add_learner_servicer

    tokens = tmp_path / "tokens.yaml"
    write_tokens(tokens)
    store = WeightStore()
    servicer = WeightServicer(store, poll_s=0.1)
    running = rpc.start_server(
        "test-learner",
        lambda s: add_learner_servicer(servicer, s),
        [learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name],
        ServerConfig(port=0, metrics_port=0, max_workers=16, grace_s=0.2),
        AuthConfig(token=ADMIN, tokens_file=tokens),
        start_metrics=False,
    )
    store.publish(1, learner_pb2.PolicySpec(kind="test", config_json="{}"), {"w": np.ones(8, np.float32)})
    subscribers = [
        WeightSubscriber(running.address(), AuthConfig(token=token), f"sub-{i}", lambda _w: None).start()
        for i, token in enumerate((EDGE, WORKER, READER))
    ]
    try:
        for sub in subscribers:
            assert sub.wait_version(1, 30), sub.client_id
    finally:
        for sub in subscribers:
            sub.stop()
        store.close()
        running.stop()


def test_workers_report_devices_and_only_workers_do(stack) -> None:
    control, _, _ = stack
    report = control_pb2.RegisterWorkerRequest(worker=control_pb2.WorkerInfo(worker_id="learner@gpu-1", kind="learner"))
    cmd = control_pb2.SendCommandRequest(command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE))
    worker, operator = control_stub(control, WORKER), control_stub(control, OPERATOR)
    assert code_of(worker.RegisterWorker, report, timeout=5) == grpc.StatusCode.OK
    assert code_of(worker.SendCommand, cmd, timeout=5) == grpc.StatusCode.PERMISSION_DENIED
    assert code_of(operator.RegisterWorker, report, timeout=5) == grpc.StatusCode.PERMISSION_DENIED
    assert code_of(control_stub(control, EDGE).RegisterWorker, report, timeout=5) == grpc.StatusCode.PERMISSION_DENIED
    workers = control_stub(control, READER).ListWorkers(control_pb2.ListWorkersRequest(), timeout=5).workers
    assert [w.worker_id for w in workers] == ["learner@gpu-1"]


def test_an_edge_writes_only_its_robots_steps(stack) -> None:
    control, replay, _ = stack
    assert connect_code(control_stub(control, ADMIN), "lab-x", "arm-5", "gripper-0") == grpc.StatusCode.OK
    assert insert_code(replay, EDGE, "arm-5") == grpc.StatusCode.OK
    assert insert_code(replay, EDGE, "gripper-0") == grpc.StatusCode.PERMISSION_DENIED
    # A denied step leaves no trace: this would-be last step does not end gripper-0's episode.
    assert insert_code(replay, EDGE, "gripper-0", index=0, last=True) == grpc.StatusCode.PERMISSION_DENIED
    assert insert_code(replay, ADMIN, "gripper-0", index=3) == grpc.StatusCode.OK
    assert insert_code(replay, READER, "arm-5") == grpc.StatusCode.PERMISSION_DENIED
    assert insert_code(replay, OPERATOR, "arm-5") == grpc.StatusCode.PERMISSION_DENIED
    stats = replay_pb2_grpc.ReplayStub(make_channel(replay.address, AuthConfig(token=READER))).Stats(
        replay_pb2.StatsRequest(), timeout=5
    )
    assert dict(stats.steps_per_robot) == {"arm-5": 1, "gripper-0": 1}


def test_whoever_may_sample_may_open_a_shared_memory_session_and_an_edge_may_not(stack) -> None:
    _, replay, _ = stack
    ask = replay_pb2.SharedMemoryRequest(host_id=host_id())

    def open_code(token: str) -> grpc.StatusCode:
        return code_of(
            replay_pb2_grpc.ReplayStub(make_channel(replay.address, AuthConfig(token=token))).OpenSharedMemory,
            ask,
            timeout=5,
        )

    assert [open_code(t) for t in (ADMIN, OPERATOR, READER, WORKER)] == [grpc.StatusCode.OK] * 4
    assert open_code(EDGE) == grpc.StatusCode.PERMISSION_DENIED


def test_tokens_rotate_without_a_restart(stack, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    control, _, tokens = stack
    # The operator's client reads its token from a file: rotating means rewriting both files.
    token_file = tmp_path / "operator.token"
    token_file.write_text(OPERATOR)
    stub = control_pb2_grpc.ControlStub(make_channel(control.address, AuthConfig(token_file=token_file)))
    req = control_pb2.ListRobotsRequest()
    assert code_of(stub.ListRobots, req, timeout=5) == grpc.StatusCode.OK
    new = "operator-token-rotated-987654321"
    write_tokens(tokens, operator=new)
    old_stub = control_stub(control, OPERATOR)
    wait_for(
        lambda: code_of(old_stub.ListRobots, req, timeout=5) == grpc.StatusCode.UNAUTHENTICATED, "old token refused"
    )
    assert code_of(control_stub(control, new).ListRobots, req, timeout=5) == grpc.StatusCode.OK
    token_file.write_text(new)
    wait_for(lambda: code_of(stub.ListRobots, req, timeout=5) == grpc.StatusCode.OK, "client picks up the new token")
    # A broken tokens file keeps the last good tokens instead of locking everyone out.
    monkeypatch.setattr(user.auth, "RELOAD_CHECK_S", 0.0)  # the next call re-reads the file
    tokens.write_text("- {role: nonsense}\n")
    assert code_of(control_stub(control, new).ListRobots, req, timeout=5) == grpc.StatusCode.OK


# --------------------------------------------------------------------------- TLS and mTLS


def make_pki(tmp_path: Path) -> dict[str, Path]:
    """A CA, a server certificate for 127.0.0.1/localhost and a client certificate with CN lab-pc-2."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    def issue(subject: str, issuer_key, issuer: x509.Name, ca: bool, san=None, usage=None):
        key = ec.generate_private_key(ec.SECP256R1())
        b = (
            x509.CertificateBuilder()
            .subject_name(name(subject))
            .issuer_name(issuer)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
        )
        if san:
            b = b.add_extension(x509.SubjectAlternativeName(san), critical=False)
        if usage:
            b = b.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        cert = b.sign(issuer_key or key, hashes.SHA256())
        return key, cert

    ca_key, ca_cert = issue("user-test-ca", None, name("user-test-ca"), ca=True)
    san = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    srv_key, srv_cert = issue("control", ca_key, ca_cert.subject, False, san, ExtendedKeyUsageOID.SERVER_AUTH)
    cli_key, cli_cert = issue("lab-pc-2", ca_key, ca_cert.subject, False, None, ExtendedKeyUsageOID.CLIENT_AUTH)
    paths = {}
    for label, obj in [("ca", ca_cert), ("server", srv_cert), ("client", cli_cert)]:
        paths[label] = tmp_path / f"{label}.pem"
        paths[label].write_bytes(obj.public_bytes(serialization.Encoding.PEM))
    for label, key in [("server_key", srv_key), ("client_key", cli_key)]:
        paths[label] = tmp_path / f"{label}.pem"
        paths[label].write_bytes(
            key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            )
        )
    return paths


def test_tls(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    cfg = server_cfg(tmp_path, tls_cert=pki["server"], tls_key=pki["server_key"])
    control = ControlService(cfg, start_metrics=False).start()
    try:
        req = control_pb2.ListRobotsRequest()
        secure = control_stub(control, READER, tls_ca=pki["ca"])
        assert code_of(secure.ListRobots, req, timeout=5) == grpc.StatusCode.OK
        plaintext = control_stub(control, READER)
        assert code_of(plaintext.ListRobots, req, timeout=2) == grpc.StatusCode.UNAVAILABLE
        (tmp_path / "other").mkdir()
        other_ca = make_pki(tmp_path / "other")["ca"]
        untrusted = control_stub(control, READER, tls_ca=other_ca)
        assert code_of(untrusted.ListRobots, req, timeout=2) == grpc.StatusCode.UNAVAILABLE
    finally:
        control.stop()


def test_mtls_and_certificate_identity(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    cfg = server_cfg(tmp_path, tls_cert=pki["server"], tls_key=pki["server_key"], tls_client_ca=pki["ca"])
    control = ControlService(cfg, start_metrics=False).start()
    try:
        req = control_pb2.ListRobotsRequest()
        # A valid token is not enough without a client certificate.
        no_cert = control_stub(control, READER, tls_ca=pki["ca"])
        assert code_of(no_cert.ListRobots, req, timeout=2) == grpc.StatusCode.UNAVAILABLE
        with_cert = dict(tls_ca=pki["ca"], tls_client_cert=pki["client"], tls_client_key=pki["client_key"])
        assert code_of(control_stub(control, READER, **with_cert).ListRobots, req, timeout=5) == grpc.StatusCode.OK
        # Without a token the certificate's name is the identity: edge lab-pc-2.
        cert_only = control_stub(control, None, enabled=False, **with_cert)
        assert connect_code(cert_only, "lab-pc-2", "arm-7") == grpc.StatusCode.OK
        assert connect_code(cert_only, "lab-pc-1", "arm-8") == grpc.StatusCode.PERMISSION_DENIED
        assert code_of(cert_only.ListRobots, req, timeout=5) == grpc.StatusCode.PERMISSION_DENIED
    finally:
        control.stop()


# --------------------------------------------------------------------------- tokens file errors never show a value

SECRET = "SECRET-x"  # in every value below: an error message must never contain it


def test_a_bad_tokens_file_names_entry_and_field_but_no_value(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens.yaml"
    entries = [
        {"token": SECRET, "role": "operator"},  # too short
        {"token": OPERATOR, "role": SECRET},  # a token pasted into the wrong field
        {"token": READER, "role": "reader", "name": [SECRET]},
        {"cert_cn": {SECRET: 1}, "role": "edge", "agent_id": "a", "robots": SECRET},
    ]
    tokens.write_text(yaml.safe_dump(entries))
    with pytest.raises(user.auth.AuthError) as err:
        user.auth.AuthTable(tokens_file=tokens)
    said = str(err.value)
    assert SECRET not in said and "input_value" not in said and "\n" not in said, said
    assert said.startswith(f"auth.tokens_file {tokens}: entry 0: token: String should have at least 16 characters; ")
    assert (
        "; entry 1: role: Input should be 'admin'" in said and "entry 2: name: Input should be a valid string" in said
    )
    assert said.endswith("; and 2 more"), said  # entry 3's cert_cn and robots: counted, not listed
    # Not YAML at all: where, without PyYAML's excerpt of the line.
    tokens.write_text(f'- {{token: "{SECRET}-0123456789, role: operator}}\n')
    with pytest.raises(user.auth.AuthError, match=r"not valid YAML: line \d+, column \d+: ") as err:
        user.auth.load_entries(tokens)
    assert SECRET not in str(err.value) and "\n" not in str(err.value)
    # Entry-level rules name the entry too.
    tokens.write_text(yaml.safe_dump([{"token": READER, "role": "reader"}, {"token": EDGE, "role": "edge"}]))
    with pytest.raises(user.auth.AuthError, match=r": entry 1: an edge entry needs agent_id$"):
        user.auth.load_entries(tokens)


def test_a_reload_of_a_bad_tokens_file_logs_no_value(
    stack, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    control, _, tokens = stack
    monkeypatch.setattr(user.auth, "RELOAD_CHECK_S", 0.0)  # every call re-reads the file
    tokens.write_text(yaml.safe_dump([{"token": SECRET, "role": "operator"}, {"token": READER, "role": SECRET}]))
    with caplog.at_level("ERROR", logger="user.auth"):
        assert code_of(control_stub(control, READER).ListRobots, control_pb2.ListRobotsRequest(), timeout=5) == (
            grpc.StatusCode.OK  # the last good tokens stay
        )
    errors = [getattr(r, "fields", {}).get("error", "") for r in caplog.records if r.name == "user.auth"]
    assert any("entry 0: token: String should have at least 16 characters" in e for e in errors), errors
    assert all(SECRET not in f"{r.getMessage()} {getattr(r, 'fields', '')}" for r in caplog.records)
