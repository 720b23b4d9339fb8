"""deploy/k8s and deploy/systemd: the manifests validate against the Kubernetes schemas (kubernetes-validate),
build with `kubectl kustomize` (skipped when kubectl is absent), and agree with the stack config and code."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

from user.config import load_config

ROOT = Path(__file__).resolve().parents[1]
BASE = ROOT / "deploy" / "k8s" / "base"
K8S_VERSION = "1.30.0"
ORGANS = {"control": 50051, "replay": 50052, "inference": 50053, "learner": 50054}


def _docs(text: str) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(text) if d]


def _resources() -> list[dict[str, Any]]:
    kustomization = yaml.safe_load((BASE / "kustomization.yaml").read_text())
    docs = []
    for name in kustomization["resources"]:
        docs += _docs((BASE / name).read_text())
    return docs


@pytest.fixture(scope="module")
def built() -> list[dict[str, Any]]:
    """The kustomize build when kubectl exists, else the resources as written (generators left out)."""
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        return _resources()
    out = subprocess.run([kubectl, "kustomize", str(BASE)], capture_output=True, text=True, timeout=120, check=True)
    return _docs(out.stdout)


def test_every_manifest_validates_against_the_kubernetes_schema() -> None:
    docs = _resources()
    assert docs
    for doc in docs:
        kubernetes_validate.validate(doc, K8S_VERSION, strict=True)


def test_kustomize_builds_and_the_build_validates() -> None:
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl not installed (Debian package kubernetes-client)")
    out = subprocess.run([kubectl, "kustomize", str(BASE)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    docs = _docs(out.stdout)
    for doc in docs:
        kubernetes_validate.validate(doc, K8S_VERSION, strict=True)
        assert doc["metadata"].get("namespace", "user") == "user" or doc["kind"] == "Namespace"
    config_maps = [d for d in docs if d["kind"] == "ConfigMap"]
    assert len(config_maps) == 1 and config_maps[0]["metadata"]["name"].startswith("user-config-")  # hashed: rolls pods


def _workload(docs: list[dict[str, Any]], name: str) -> dict[str, Any]:
    (found,) = [d for d in docs if d["kind"] in ("Deployment", "StatefulSet") and d["metadata"]["name"] == name]
    return found


def test_workloads_match_the_stack_config(built: list[dict[str, Any]]) -> None:
    cfg = load_config(BASE / "stack.yaml", environ={})
    assert cfg.auth.tokens_file is not None
    for organ, port in ORGANS.items():
        section = getattr(cfg, organ)
        assert (section.server.port, section.server.host) == (port, "0.0.0.0")
        pod = _workload(built, organ)["spec"]["template"]
        (container,) = pod["spec"]["containers"]
        assert container["args"][0] == organ
        ports = {p["name"]: p["containerPort"] for p in container["ports"]}
        assert ports == {"grpc": port, "metrics": section.server.metrics_port}
        # Health through the gRPC health service (open without a token), scraped by Prometheus.
        assert container["readinessProbe"]["grpc"]["port"] == port
        assert container["livenessProbe"]["grpc"]["port"] == port
        notes = pod["metadata"]["annotations"]
        assert notes["prometheus.io/scrape"] == "true" and notes["prometheus.io/port"] == str(ports["metrics"])
        env = {e["name"]: e for e in container["env"]}
        assert env["USER_TOKEN"]["valueFrom"]["secretKeyRef"]["name"] == "user-tokens"
        mounts = {m["mountPath"] for m in container["volumeMounts"]}
        assert str(cfg.auth.tokens_file.parent) in mounts
    # Addresses name the Services.
    services = {d["metadata"]["name"] for d in built if d["kind"] == "Service"}
    for addr in (
        cfg.replay.control_addr,
        cfg.learner.replay_addr,
        cfg.inference.learner_addr,
        cfg.learner.control_addr,
    ):
        assert addr.split(":")[0] in services


def test_replay_is_a_statefulset_with_a_volume_per_shard(built: list[dict[str, Any]]) -> None:
    replay = _workload(built, "replay")
    assert replay["kind"] == "StatefulSet"
    (claim,) = replay["spec"]["volumeClaimTemplates"]
    (container,) = replay["spec"]["template"]["spec"]["containers"]
    mount = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}[claim["metadata"]["name"]]
    assert mount == str(load_config(BASE / "stack.yaml", environ={}).replay.path)
    assert replay["spec"]["serviceName"] in {d["metadata"]["name"] for d in built if d["kind"] == "Service"}


def test_learner_and_inference_request_gpus_and_control_keeps_its_state(built: list[dict[str, Any]]) -> None:
    for organ in ("learner", "inference"):
        (container,) = _workload(built, organ)["spec"]["template"]["spec"]["containers"]
        assert container["resources"]["limits"]["nvidia.com/gpu"] == 1
    cfg = load_config(BASE / "stack.yaml", environ={})
    assert cfg.learner.device.startswith("cuda") and cfg.inference.device.startswith("cuda")
    control = _workload(built, "control")
    (container,) = control["spec"]["template"]["spec"]["containers"]
    mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
    assert str(cfg.control.state_path).startswith(mounts["data"])
    assert control["spec"]["strategy"]["type"] == "Recreate"


def test_network_policies_deny_by_default_and_open_grpc_and_metrics(built: list[dict[str, Any]]) -> None:
    policies = {d["metadata"]["name"]: d["spec"] for d in built if d["kind"] == "NetworkPolicy"}
    deny = policies["default-deny-ingress"]
    assert deny["podSelector"] == {} and "ingress" not in deny
    ports = {p["port"] for spec in policies.values() for rule in spec.get("ingress", []) for p in rule["ports"]}
    assert ports == {"grpc", "metrics"}


# --------------------------------------------------------------------------- systemd


def test_systemd_unit_restarts_and_logs_to_journald() -> None:
    from user.edge_setup import render_unit

    unit = render_unit(userctl="/opt/user/.venv/bin/userctl", config="/etc/user/edge.yaml", user="robot")
    for line in [
        "ExecStart=/opt/user/.venv/bin/userctl edge --config /etc/user/edge.yaml",
        "Restart=on-failure",
        "StandardOutput=journal",
        "User=robot",
        "KillSignal=SIGTERM",
        "WantedBy=multi-user.target",
    ]:
        assert line in unit.splitlines(), line
    shipped = (ROOT / "deploy" / "systemd" / "user-edge.service").read_text()
    assert shipped.endswith(render_unit("/opt/user/.venv/bin/userctl", "/etc/user/edge.yaml", "robot"))


def test_systemd_accepts_the_unit(tmp_path: Path) -> None:
    from user.edge_setup import render_unit

    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not installed")
    userctl = ROOT / ".venv" / "bin" / "userctl"  # verify checks that ExecStart exists
    unit = tmp_path / "user-edge.service"
    unit.write_text(render_unit(str(userctl), str(tmp_path / "edge.yaml"), "root"))
    out = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and not out.stderr.strip(), out.stderr


def test_install_service_writes_the_unit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import getpass
    import sys

    from user import cli, edge_setup

    # tmp_path is under /tmp, which the unit (PrivateTmp=yes) refuses; the next test checks that refusal.
    monkeypatch.setattr(edge_setup, "_hidden_by_private_tmp", lambda config: "")
    config = tmp_path / "edge.yaml"
    config.write_text(edge_setup.discover("cloud.lab:50051", ["sim_reach_arm"], serial=list, cameras=list))
    units = tmp_path / "units"
    units.mkdir()
    args = ["edge", "install-service", "-c", str(config), "--unit-dir", str(units), "--user", getpass.getuser()]
    assert cli.main([*args, "--dry-run", "--userctl", sys.executable]) == 0
    out = capsys.readouterr().out
    assert "ExecStart=" in out and "WARNING" not in out and not (units / "user-edge.service").exists()
    assert cli.main([*args, "--no-start", "--userctl", sys.executable]) == 0
    unit = (units / "user-edge.service").read_text().splitlines()
    assert f"ExecStart={sys.executable} edge --config {config}" in unit
    assert "WorkingDirectory=/var/lib/user-edge" in unit and "StateDirectory=user-edge" in unit


def test_install_service_refuses_a_config_the_service_cannot_see(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The unit runs with PrivateTmp=yes: a config under /tmp would be missing when the service starts."""
    from user import cli

    config = Path("/tmp") / "edge.yaml"
    args = ["edge", "install-service", "-c", str(config), "--unit-dir", str(tmp_path), "--user", "robot"]
    assert cli.main([*args, "--no-start"]) == 2
    assert "PrivateTmp=yes" in capsys.readouterr().err and not (tmp_path / "user-edge.service").exists()
    assert cli.main([*args, "--dry-run"]) == 0
    assert "# WARNING: /tmp/edge.yaml is under a temporary directory" in capsys.readouterr().out


# --------------------------------------------------------------------------- edge discover


def test_discover_finds_arms_and_cameras_and_prints_a_config_that_loads(tmp_path: Path) -> None:
    from user.config import StackConfig
    from user.edge_setup import discover, find_serial_ports

    # A fake /dev and /sys: one SO-101 bus adapter (CH343) and one unknown USB serial device.
    dev, sys_tty = tmp_path / "dev", tmp_path / "sys" / "class" / "tty"
    usb = tmp_path / "sys" / "devices" / "usb1" / "1-1"
    for name, (vid, pid) in {"ttyACM0": ("1a86", "55d3"), "ttyUSB0": ("10c4", "ea60")}.items():
        (dev / name).parent.mkdir(parents=True, exist_ok=True)
        (dev / name).touch()
        device = usb / name / "1-1:1.0"
        device.mkdir(parents=True)
        (usb / name / "idVendor").write_text(vid + "\n")
        (usb / name / "idProduct").write_text(pid + "\n")
        (sys_tty / name).mkdir(parents=True)
        (sys_tty / name / "device").symlink_to(device)
    ports = find_serial_ports(dev, sys_tty)
    assert [(p.device.rsplit("/", 1)[-1], p.vid, bool(p.arm_bridge)) for p in ports] == [
        ("ttyACM0", "1a86", True),
        ("ttyUSB0", "10c4", False),
    ]
    camera = {"id": "/dev/video0", "default_stream_profile": {"width": 640, "height": 480, "fps": 30}}
    text = discover("cloud.lab:50051", ["sim_reach_arm"], serial=lambda: ports, cameras=lambda: [camera])
    assert "/dev/video0  640x480 @ 30 fps" in text and "port: " + ports[0].device in text
    cfg = StackConfig.model_validate(yaml.safe_load(text))  # ready: the agent accepts it as is
    assert [(r.id, r.kind) for r in cfg.edge.robots] == [("sim-reach-arm-0", "sim_reach_arm")]
    assert cfg.edge.control_addr == "cloud.lab:50051" and cfg.edge.replay_addr == "cloud.lab:50052"
    with pytest.raises(ValueError, match="unknown simulated robot kind"):
        discover("x:1", ["no_such_robot"], serial=list, cameras=list)
