"""Operating the stack: tokens that cannot start a service (placeholders, unreadable token files) fail with one line
naming the setting; the k8s base ships no secret and its overlays build; every metric the Grafana dashboard and the
Prometheus alerts use is one the code defines, with the labels and type the queries assume; the compose Grafana
needs a password; secrets stay out of git and the image; robot PCs keep their token in one documented place."""

from __future__ import annotations

import ast
import contextlib
import functools
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

from tests.helpers import free_port, wait_for
from tests.test_compose import _ignored
from user import auth as user_auth
from user import edge_setup
from user.auth import AuthTable
from user.config import AuthConfig, ConfigError, ServerConfig, StackConfig
from user.rpc import start_server

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"
PROM = ROOT / "deploy" / "prometheus"
DASHBOARD = ROOT / "deploy" / "grafana" / "dashboards" / "user-stack.json"
SOURCE_DIRS = ("user", "services", "cloud_learner", "edge_agent")
TARGET_LABELS = {"job", "instance"}  # added by Prometheus to every series
PLACEHOLDER = "REPLACE-ME-operator-token-0001"
ORGANS = {"control": 50051, "replay": 50052, "inference": 50053, "learner": 50054}


@pytest.fixture(autouse=True)
def _no_token_in_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in list(os.environ):
        if key == "USER_TOKEN" or key.startswith("USER__"):
            monkeypatch.delenv(key)


def _serve(auth: AuthConfig) -> Any:
    return start_server("probe", lambda _server: None, [], ServerConfig(port=0), auth, start_metrics=False)


def _userctl(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "USER_TOKEN" and not k.startswith("USER__")}
    return subprocess.run(
        [sys.executable, "-m", "user.cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )


# --------------------------------------------------------------------------- placeholder tokens


@pytest.mark.parametrize("placeholder", [PLACEHOLDER, "a-long-token-with-replace-me-inside"])
def test_a_placeholder_in_the_tokens_file_stops_the_server_naming_the_entry(tmp_path: Path, placeholder: str) -> None:
    tokens = tmp_path / "tokens.yaml"
    tokens.write_text(
        f"- {{token: a-real-operator-token-0123, role: operator}}\n- {{token: {placeholder}, role: reader}}\n"
    )
    with pytest.raises(ConfigError) as err:
        _serve(AuthConfig(token="a-real-admin-token-0123", tokens_file=tokens))
    assert f"auth.tokens_file {tokens}: entry 1: token is an example placeholder" in str(err.value)
    assert placeholder not in str(err.value)


def test_a_placeholder_shared_token_stops_servers_and_clients_naming_the_setting(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("USER_TOKEN", PLACEHOLDER)
    for failing in (lambda: _serve(AuthConfig()), AuthConfig().resolved_token):
        with pytest.raises(ConfigError, match=r"^auth\.token \(\$USER_TOKEN\): the token is an example placeholder"):
            failing()
    monkeypatch.delenv("USER_TOKEN")
    token_file = tmp_path / "admin.token"
    token_file.write_text(PLACEHOLDER.lower() + "\n")
    for failing in (
        lambda: _serve(AuthConfig(token_file=token_file)),
        AuthConfig(token_file=token_file).resolved_token,
    ):
        with pytest.raises(ConfigError, match=r"^auth\.token_file: the token is an example placeholder") as err:
            failing()
        assert PLACEHOLDER.lower() not in str(err.value)


def test_a_placeholder_rotated_in_keeps_the_previous_tokens(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(user_auth, "RELOAD_CHECK_S", 0.0)  # look at the file on every call
    tokens = tmp_path / "tokens.yaml"
    tokens.write_text("- {token: the-first-operator-token, role: operator}\n")
    table = AuthTable(tokens_file=tokens)
    tokens.write_text(f"- {{token: {PLACEHOLDER}, role: operator, name: rotated}}\n")
    assert table.identify(f"Bearer {PLACEHOLDER}", []) is None
    assert table.identify("Bearer the-first-operator-token", []).role == "operator"


# --------------------------------------------------------------------------- auth.token_file


@pytest.mark.parametrize("problem", ["missing", "directory", "empty"])
def test_an_unusable_token_file_is_a_config_error_naming_it(tmp_path: Path, problem: str) -> None:
    path = tmp_path / "edge.token"
    if problem == "directory":
        path.mkdir()
    elif problem == "empty":
        path.write_text("\n")
    why = {"missing": "No such file or directory", "directory": "Is a directory", "empty": "the file is empty"}
    with pytest.raises(ConfigError, match=rf"^auth\.token_file {re.escape(str(path))}: .*{why[problem]}"):
        AuthConfig(token_file=path).resolved_token()


def test_userctl_exits_2_with_one_line_for_a_missing_token_file(tmp_path: Path) -> None:
    """What a systemd unit's journal shows: one line naming the setting, exit 2, no traceback."""
    missing = tmp_path / "nope" / "edge.token"
    spool = f"edge.spool_dir={tmp_path / 'spool'}"
    for args in (["edge", "--set", spool], ["control", "--set", "control.server.port=0"], ["robots", "ls"]):
        out = _userctl(*args, "--set", f"auth.token_file={missing}", "--set", "control.server.metrics_port=0")
        assert out.returncode == 2, (args, out.stderr)
        line = out.stderr.strip().splitlines()[-1]
        assert f"auth.token_file {missing}: cannot read it (No such file or directory)" in line, out.stderr
        assert "Traceback" not in out.stderr


def test_userctl_health_needs_no_token_even_when_the_token_file_is_bad(tmp_path: Path) -> None:
    server = _serve(AuthConfig(token="the-servers-token-0123"))
    bad = ["--set", f"auth.token_file={tmp_path / 'missing.token'}", "--timeout", "10"]
    try:
        out = _userctl("health", f"127.0.0.1:{server.port}", *bad)
        assert out.returncode == 0 and out.stdout.strip() == f"127.0.0.1:{server.port}: SERVING", out
    finally:
        server.stop()
    port = free_port()
    out = _userctl("health", f"127.0.0.1:{port}", *bad)
    assert out.returncode == 1 and f"127.0.0.1:{port}: unreachable" in out.stdout, out
    assert "Traceback" not in out.stderr


# --------------------------------------------------------------------------- robot PCs: one token location


def test_discover_install_service_and_the_docs_agree_on_the_token_location(tmp_path: Path) -> None:
    text = edge_setup.discover("cloud.lab:50051", ["sim_reach_arm"], serial=list, cameras=list)
    cfg = StackConfig.model_validate(yaml.safe_load(text))
    assert cfg.auth.enabled and cfg.auth.token is None and cfg.auth.token_file is None
    assert f"USER_TOKEN=<this PC's edge token> in {edge_setup.ENV_FILE}" in text
    assert "\n  metrics_host: 127.0.0.1\n" in text and "0.0.0.0 lets the lab's Prometheus" in text
    unit = (ROOT / "deploy" / "systemd" / "user-edge.service").read_text()
    assert f"EnvironmentFile=-{edge_setup.ENV_FILE}" in unit and f"USER_TOKEN=... in {edge_setup.ENV_FILE}" in unit
    for doc in ("README.md", "docs/notes/ops.md"):
        assert f"`USER_TOKEN=<its edge token>` in `{edge_setup.ENV_FILE}`" in (ROOT / doc).read_text(), doc
    assert "edge.token" not in text + unit


def _install(config: Path, env_file: Path, *extra: str) -> int:
    from user import cli

    args = ["edge", "install-service", "-c", str(config), "--unit-dir", str(config.parent), "--no-start"]
    return cli.main([*args, "--env-file", str(env_file), "--userctl", sys.executable, *extra])


@pytest.fixture
def edge_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(edge_setup, "_hidden_by_private_tmp", lambda path: "")  # tmp_path is under /tmp
    config = tmp_path / "edge.yaml"
    config.write_text(edge_setup.discover("cloud.lab:50051", ["sim_reach_arm"], serial=list, cameras=list))
    return config


def test_install_service_refuses_a_token_file_the_service_cannot_read(
    edge_config: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = edge_config.parent / "edge.token"
    edge_config.write_text(edge_config.read_text().replace("enabled: true", f"enabled: true\n  token_file: {missing}"))
    env_file = edge_config.parent / "edge.env"
    assert _install(edge_config, env_file, "--user", "root") == 2
    err = capsys.readouterr().err.strip()
    assert f"auth.token_file {missing}: cannot read it (No such file or directory)" in err and "\n" not in err
    assert not (edge_config.parent / "user-edge.service").exists()
    env_file.write_text("USER_TOKEN=a-real-edge-token-0123\n")  # $USER_TOKEN wins over the file: it will start
    assert _install(edge_config, env_file, "--user", "root") == 0
    unit = (edge_config.parent / "user-edge.service").read_text()
    assert f"EnvironmentFile=-{env_file}" in unit


def test_install_service_refuses_a_placeholder_and_explains_a_missing_token(
    edge_config: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    env_file = edge_config.parent / "edge.env"
    env_file.write_text(f"# the edge's token\nUSER_TOKEN='{PLACEHOLDER}'\n")
    assert _install(edge_config, env_file, "--user", "root") == 2
    err = capsys.readouterr().err
    assert f"{env_file}: USER_TOKEN is an example placeholder" in err and PLACEHOLDER not in err
    env_file.unlink()  # no token anywhere yet: installed (it may come later), and said how to give one
    assert _install(edge_config, env_file, "--user", "root", "--dry-run") == 0
    assert f"# NOTE: the config names no token: put USER_TOKEN=<this PC's edge token> in {env_file}" in (
        capsys.readouterr().out
    )
    assert _install(edge_config, env_file, "--user", "root") == 0
    assert "note: the config names no token" in capsys.readouterr().err


# --------------------------------------------------------------------------- kubernetes


def _docs(text: str) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(text) if d]


def test_the_base_ships_no_secret_and_the_token_files_are_git_ignored() -> None:
    kustomization = yaml.safe_load((K8S / "base" / "kustomization.yaml").read_text())
    assert "secretGenerator" not in kustomization
    for name in kustomization["resources"]:
        assert all(d["kind"] != "Secret" for d in _docs((K8S / "base" / name).read_text())), name
    for path in K8S.rglob("*.y*ml"):  # the values (comments may name the marker)
        assert "REPLACE-ME" not in json.dumps(_docs(path.read_text())), f"{path} ships a placeholder token"
    tokens = K8S / "components" / "tokens"
    generator = yaml.safe_load((tokens / "kustomization.yaml").read_text())["secretGenerator"][0]
    for name in [*generator["envs"], *generator["files"]]:
        assert (tokens / f"{name}.example").is_file()
        if shutil.which("git") and (ROOT / ".git").exists():
            path = str((tokens / name).relative_to(ROOT))
            assert subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT).returncode == 0, path


def _build_overlay(tmp_path: Path, overlay: str) -> list[dict[str, Any]]:
    """kubectl kustomize of a copy of deploy/k8s with token files made as the component's README says."""
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl not installed (Debian package kubernetes-client)")
    tree = tmp_path / "k8s"
    shutil.copytree(K8S, tree)
    tokens = tree / "components" / "tokens"
    (tokens / "tokens.env").write_text("admin-token=" + "ab" * 32 + "\n")
    (tokens / "tokens.yaml").write_text("- {token: a-real-operator-token-0123, role: operator}\n")
    out = subprocess.run([kubectl, "kustomize", str(tree / "overlays" / overlay)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    docs = _docs(out.stdout)
    for doc in docs:
        kubernetes_validate.validate(doc, "1.30.0", strict=True)
    return docs


def _secret_refs(docs: list[dict[str, Any]]) -> set[tuple[str, str]]:
    refs = set()
    for doc in docs:
        if doc["kind"] in ("Deployment", "StatefulSet"):
            pod = doc["spec"]["template"]["spec"]
            refs |= {
                (v["secret"]["secretName"], i["key"])
                for v in pod["volumes"]
                if "secret" in v
                for i in v["secret"]["items"]
            }
            for env in pod["containers"][0]["env"]:
                ref = env["valueFrom"]["secretKeyRef"]
                refs.add((ref["name"], ref["key"]))
    return refs


def test_the_edge_access_overlay_has_the_secret_and_a_load_balancer_per_organ(tmp_path: Path) -> None:
    docs = _build_overlay(tmp_path, "edge-access")
    (secret,) = [d for d in docs if d["kind"] == "Secret"]
    assert {(secret["metadata"]["name"], key) for key in secret["data"]} == _secret_refs(docs)
    outside = {d["metadata"]["name"]: d["spec"] for d in docs if d["kind"] == "Service" and d["spec"].get("type")}
    assert set(outside) == {f"{organ}-edge" for organ in ORGANS}
    for organ, port in ORGANS.items():
        spec = outside[f"{organ}-edge"]
        assert spec["type"] == "LoadBalancer" and spec["selector"] == {"app.kubernetes.io/name": organ}
        assert [(p["port"], p["targetPort"]) for p in spec["ports"]] == [(port, "grpc")]  # no /metrics outside
    assert all(d["metadata"].get("namespace") == "user" for d in docs if d["kind"] != "Namespace")


def test_the_replay_shards_overlay_addresses_every_shard(tmp_path: Path) -> None:
    docs = _build_overlay(tmp_path, "replay-shards")
    (replay,) = [d for d in docs if d["kind"] == "StatefulSet"]
    replicas = replay["spec"]["replicas"]
    (config_map,) = [d for d in docs if d["kind"] == "ConfigMap"]
    cfg = StackConfig.model_validate(yaml.safe_load(config_map["data"]["stack.yaml"]))
    headless = replay["spec"]["serviceName"]
    assert cfg.learner.replay_addrs == [f"replay-{i}.{headless}:50052" for i in range(replicas)]
    assert cfg.control.replay_shards and cfg.control.replay_shards[-1].agents == ["*"]  # no edge left on "replay"
    services = {d["metadata"]["name"]: d["spec"] for d in docs if d["kind"] == "Service"}
    assert "replay-edge" not in services
    for i in range(replicas):
        assert services[f"replay-{i}-edge"]["selector"]["statefulset.kubernetes.io/pod-name"] == f"replay-{i}"


def test_slow_starting_organs_get_a_startup_probe() -> None:
    for organ in ("learner", "inference"):
        (workload,) = [d for d in _docs((K8S / "base" / f"{organ}.yaml").read_text()) if d["kind"] == "Deployment"]
        (container,) = workload["spec"]["template"]["spec"]["containers"]
        probe = container["startupProbe"]
        assert probe["grpc"]["port"] == ORGANS[organ]
        assert probe["periodSeconds"] * probe["failureThreshold"] >= 300, "five minutes to import torch"


def test_the_k8s_scrape_config_names_jobs_by_the_pod_label_the_manifests_set() -> None:
    scrape = yaml.safe_load((K8S / "prometheus-scrape.yaml").read_text())
    jobs = {job["job_name"]: job for job in scrape["scrape_configs"]}
    relabel = jobs["user-pods"]["relabel_configs"]
    (to_job,) = [r for r in relabel if r.get("target_label") == "job"]
    assert to_job["source_labels"] == ["__meta_kubernetes_pod_label_app_kubernetes_io_name"]
    for organ in ORGANS:
        (workload,) = [
            d for d in _docs((K8S / "base" / f"{organ}.yaml").read_text()) if d["kind"] in ("Deployment", "StatefulSet")
        ]
        assert workload["spec"]["template"]["metadata"]["labels"]["app.kubernetes.io/name"] == organ
    assert "edge" in jobs and "file_sd_configs" in jobs["edge"]


# --------------------------------------------------------------------------- metrics: dashboard and alerts


@functools.cache
def _defined_metrics() -> dict[str, tuple[str, set[str]]]:
    """name -> (prometheus_client type, label names) of every metric object the code creates."""
    found: dict[str, tuple[str, set[str]]] = {}
    kinds = ("Counter", "Gauge", "Histogram", "Summary")
    for folder in SOURCE_DIRS:
        for path in (ROOT / folder).rglob("*.py"):
            if "v1" in path.parts:
                continue
            tree = ast.parse(path.read_text())
            constants = {
                t.id: node.value
                for node in tree.body
                if isinstance(node, ast.Assign)
                for t in node.targets
                if isinstance(t, ast.Name)
            }
            for node in ast.walk(tree):
                if not (isinstance(node, ast.Call) and getattr(node.func, "attr", None) in kinds and node.args):
                    continue
                name = node.args[0]
                if not (isinstance(name, ast.Constant) and str(name.value).startswith("user_")):
                    continue
                labels = node.args[2] if len(node.args) > 2 else None
                labels = next((k.value for k in node.keywords if k.arg == "labelnames"), labels)
                if isinstance(labels, ast.Name):
                    labels = constants[labels.id]
                found[name.value] = (node.func.attr, set(ast.literal_eval(labels)) if labels is not None else set())
    return found


def _resolve(name: str, defined: dict[str, tuple[str, set[str]]]) -> tuple[str, set[str]]:
    """The definition behind a series name: as written, or a counter's _total, a histogram's _bucket/_sum/_count."""
    if name in defined:
        return defined[name]
    base, _, suffix = name.rpartition("_")
    kind, labels = defined.get(base, ("", set()))
    if (suffix == "total" and kind == "Counter") or (suffix in ("sum", "count") and kind in ("Histogram", "Summary")):
        return kind, labels
    if suffix == "bucket" and kind == "Histogram":
        return "Histogram", labels | {"le"}
    raise AssertionError(f"{name} is not defined by any prometheus_client object in {SOURCE_DIRS}")


def _dashboard_panels() -> list[dict[str, Any]]:
    dash = json.loads(DASHBOARD.read_text())
    return [p for top in dash["panels"] for p in [top, *top.get("panels", [])]]


def _queries() -> list[tuple[str, str]]:
    """(where, PromQL) of every dashboard target and alert rule."""
    queries = [(f"panel {p['title']!r}", t["expr"]) for p in _dashboard_panels() for t in p.get("targets", [])]
    rules = yaml.safe_load((PROM / "rules.yml").read_text())
    queries += [(f"alert {r['alert']}", r["expr"]) for g in rules["groups"] for r in g["rules"]]
    return queries


def test_every_metric_the_dashboard_and_alerts_use_is_defined_with_those_labels() -> None:
    defined = _defined_metrics()
    assert defined["user_learner_experiment_failed"] == ("Gauge", {"experiment"})
    for where, expr in _queries():
        used = {name: _resolve(name, defined) for name in re.findall(r"\buser_[a-z0-9_]+", expr)}
        assert used or "up" in expr, where
        known = TARGET_LABELS | {label for _, labels in used.values() for label in labels}
        grouped = {g.strip() for by in re.findall(r"\b(?:by|on)\s*\(([^)]*)\)", expr) for g in by.split(",")}
        matched = set(re.findall(r"([a-z_]+)\s*(?:=~|!~|!=|=)\s*\"", expr))
        assert (grouped | matched) - {""} <= known, f"{where}: labels {(grouped | matched) - known} not on {used}"


def test_rate_and_increase_only_of_counters_and_counters_only_through_them() -> None:
    defined = _defined_metrics()
    for where, expr in _queries():
        for name in re.findall(r"\b(?:rate|increase)\(\s*(user_[a-z0-9_]+)", expr):
            kind = _resolve(name, defined)[0]
            assert kind == "Counter" or name.endswith(("_bucket", "_sum", "_count")), f"{where}: rate of {kind} {name}"
        for match in re.finditer(r"\buser_[a-z0-9_]+", expr):
            if _resolve(match.group(), defined)[0] == "Counter":
                before = expr[: match.start()].rstrip()
                assert before.endswith(("rate(", "increase(")), f"{where}: counter {match.group()} read raw"


def test_the_health_row_shows_what_loses_data() -> None:
    panels = _dashboard_panels()
    (row,) = [p for p in panels if p["type"] == "row" and p["title"] == "Health / data loss"]
    below = [p for p in panels if p["type"] != "row" and p["gridPos"]["y"] > row["gridPos"]["y"]]
    shown = {n for p in below for t in p["targets"] for n in re.findall(r"\buser_[a-z0-9_]+", t["expr"])}
    assert shown >= {
        "user_edge_control_connected",
        "user_control_lease_expirations_total",
        "user_edge_steps_rejected_total",
        "user_edge_spool_quarantined_steps",
        "user_edge_spool_bytes",
        "user_edge_non_finite_actions_total",
        "user_inference_non_finite_actions_total",
        "user_weights_rejected_total",
        "user_learner_sample_errors_total",
        "user_learner_replay_shard_up",
        "user_replay_bytes_on_disk",
        "user_replay_rate_limited_total",
        "user_edge_loop_overruns_total",
        "user_grpc_client_errors_total",
        "user_learner_experiment_failed",
    }


def test_dashboard_ids_are_unique_and_panels_do_not_overlap() -> None:
    panels = _dashboard_panels()
    ids = [p["id"] for p in panels]
    assert len(ids) == len(set(ids)), sorted(i for i in ids if ids.count(i) > 1)
    cells: dict[tuple[int, int], str] = {}
    for p in panels:
        assert len({t["refId"] for t in p.get("targets", [])}) == len(p.get("targets", [])), p["title"]
        g = p["gridPos"]
        for cell in ((x, y) for x in range(g["x"], g["x"] + g["w"]) for y in range(g["y"], g["y"] + g["h"])):
            assert cell not in cells, f"{p['title']!r} overlaps {cells[cell]!r}"
            cells[cell] = p["title"]


def _streaming_methods() -> set[str]:
    methods = set()
    for proto in (ROOT / "proto").rglob("*.proto"):
        text = proto.read_text()
        package = re.search(r"^package\s+([\w.]+);", text, re.M).group(1)
        for service, body in re.findall(r"service\s+(\w+)\s*\{(.*?)\n\}", text, re.S):
            for method, req, resp in re.findall(r"rpc\s+(\w+)\s*\(([^)]*)\)\s*returns\s*\(([^)]*)\)", body):
                if "stream " in f"{req} {resp} ":
                    methods.add(f"/{package}.{service}/{method}")
    return methods


def test_unary_latency_leaves_out_every_streaming_rpc() -> None:
    streaming = _streaming_methods() | {"/grpc.health.v1.Health/Watch"}
    assert "/user.v1.Replay/InsertBatch" in streaming
    (panel,) = [p for p in _dashboard_panels() if p["title"] == "Unary RPC latency p99"]
    (regex,) = re.findall(r'method!~"([^"]+)"', panel["targets"][0]["expr"])
    for method in streaming:  # PromQL anchors regexes at both ends, as fullmatch does
        assert re.fullmatch(regex, method), f"{method} (a stream) is in the unary latency"
    for unary in ("/user.v1.Replay/Sample", "/user.v1.Inference/Act", "/user.v1.Control/ListRobots"):
        assert not re.fullmatch(regex, unary), unary


def test_rules_load_into_prometheus_and_every_alert_says_what_and_how_bad() -> None:
    rules = yaml.safe_load((PROM / "rules.yml").read_text())
    alerts = [r for g in rules["groups"] for r in g["rules"]]
    assert len({a["alert"] for a in alerts}) == len(alerts)
    for alert in alerts:
        assert alert["labels"]["severity"] in ("critical", "warning") and alert["annotations"]["summary"], alert
    prom = yaml.safe_load((ROOT / "deploy" / "prometheus.yml").read_text())
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    mounts = dict(reversed(v.split(":")[:2]) for v in compose["services"]["prometheus"]["volumes"])
    files = [
        *prom["rule_files"],
        *(f for j in prom["scrape_configs"] for sd in j.get("file_sd_configs", []) for f in sd["files"]),
    ]
    for path in files:  # each resolves through a compose mount to a file of the repo
        folder, name = path.rsplit("/", 1)
        assert (ROOT / mounts[folder] / name).is_file(), path


def test_promtool_accepts_the_rules_and_parses_every_dashboard_query(tmp_path: Path) -> None:
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool not installed (Debian package prometheus)")
    grafana = {"$__rate_interval": "1m", "$robot": ".*"}  # what Grafana substitutes before Prometheus parses
    exprs = [expr for where, expr in _queries() if where.startswith("panel")]
    for var, value in grafana.items():
        exprs = [e.replace(var, value) for e in exprs]
    recorded = [{"record": f"dashboard:query{i}", "expr": e} for i, e in enumerate(exprs)]
    (tmp_path / "dashboard.yml").write_text(yaml.safe_dump({"groups": [{"name": "dashboard", "rules": recorded}]}))
    for rules in (PROM / "rules.yml", tmp_path / "dashboard.yml"):
        out = subprocess.run([promtool, "check", "rules", str(rules)], capture_output=True, text=True)
        assert out.returncode == 0, out.stdout + out.stderr


# --------------------------------------------------------------------------- the learner's failed-experiment gauge


def test_an_experiment_that_cannot_start_sets_its_failed_gauge(tmp_path: Path) -> None:
    from prometheus_client import REGISTRY

    import tests.plugins  # noqa: F401 - the test_mean algorithm
    from tests.test_experiments import stack_cfg
    from user.config import RobotConfig

    experiments = [
        {"name": "ops_mixed", "robots": {"ids": ["arm-0", "panda-0"]}, "algorithm": {"kind": "test_mean"}},
        {"name": "ops_solo", "robots": {"ids": ["arm-1"]}, "algorithm": {"kind": "test_mean"}},
    ]
    cfg = stack_cfg(tmp_path, experiments)
    robots = [("arm-0", "sim_reach_arm"), ("panda-0", "gym_hil_panda"), ("arm-1", "sim_reach_arm")]
    cfg.edge.robots = [RobotConfig(id=rid, kind=kind, params={"max_episode_steps": 20}) for rid, kind in robots]
    names = ("ops_mixed", "ops_solo")

    def gauges() -> tuple[float | None, ...] | None:
        values = tuple(REGISTRY.get_sample_value("user_learner_experiment_failed", {"experiment": n}) for n in names)
        return values if None not in values else None

    with _learning_stack(cfg):
        assert wait_for(gauges, "both experiments to be started or failed") == (1.0, 0.0)


@contextlib.contextmanager
def _learning_stack(cfg: StackConfig) -> Iterator[None]:
    """Control, replay, learner and an edge agent (no inference: its robots hold, which is enough to register)."""
    from cloud_learner.server import LearnerService
    from edge_agent.agent import EdgeAgent
    from services.control.server import ControlService
    from services.replay.server import ReplayService

    with contextlib.ExitStack() as stack:
        control = ControlService(cfg, start_metrics=False).start()
        stack.callback(control.stop)
        cfg.replay.control_addr = cfg.learner.control_addr = cfg.edge.control_addr = control.address
        replay = ReplayService(cfg, start_metrics=False).start()
        stack.callback(replay.stop)
        cfg.learner.replay_addr = cfg.edge.replay_addr = replay.address
        learner = LearnerService(cfg, start_metrics=False).start()
        stack.callback(learner.stop)
        cfg.edge.learner_addr, cfg.edge.inference_addr = learner.address, f"127.0.0.1:{free_port()}"
        cfg.edge.mode, cfg.edge.metrics_port, cfg.edge.spool_dir = "fast", 0, None
        agent = EdgeAgent(cfg)
        agent.start()
        stack.callback(agent.stop)
        yield


# --------------------------------------------------------------------------- compose, git and image hygiene


def _grafana_guard() -> str:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    grafana = compose["services"]["grafana"]
    assert grafana["environment"]["GF_SECURITY_ADMIN_PASSWORD"] == "${GRAFANA_ADMIN_PASSWORD:-}"  # no default
    shell, flag, script, _name = grafana["entrypoint"]
    assert (shell, flag) == ("/bin/sh", "-c") and "exec /run.sh" in script
    return script.replace("$$", "$").replace("exec /run.sh", "exec true")  # compose unescapes $$; no Grafana here


@pytest.mark.parametrize("password, starts", [("", False), ("admin", False), ("a-real-password", True)])
def test_grafana_does_not_start_without_a_password(password: str, starts: bool) -> None:
    env = {"PATH": os.environ["PATH"], "GF_SECURITY_ADMIN_PASSWORD": password}
    out = subprocess.run(["/bin/sh", "-c", _grafana_guard(), "grafana"], env=env, capture_output=True, text=True)
    assert (out.returncode == 0) == starts and (("set GRAFANA_ADMIN_PASSWORD" in out.stderr) != starts), out


SECRETS = [".env", "deploy/k8s/components/tokens/tokens.env", "certs/server.key", "ca.pem", "edge.token", "tokens.yaml"]
KEPT = ["user/auth.py", "tests/test_auth.py", "deploy/k8s/components/tokens/tokens.env.example", "configs/demo.yaml"]


def test_secrets_stay_out_of_git_and_the_image_and_sources_stay_in() -> None:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    for path in SECRETS:
        assert _ignored(path, patterns) and _ignored(f"services/{path}", patterns), f".dockerignore keeps {path}"
    for path in ("user/auth.py", "services/replay/server.py", "README.md"):
        assert not _ignored(path, patterns), f".dockerignore drops {path}"
    if not (shutil.which("git") and (ROOT / ".git").exists()):
        pytest.skip("not a git checkout")
    check = subprocess.run(
        ["git", "check-ignore", "--no-index", *SECRETS, *KEPT], cwd=ROOT, capture_output=True, text=True
    )
    assert set(check.stdout.split()) == set(SECRETS)
    tracked = subprocess.run(["git", "ls-files", "-ci", "--exclude-standard"], cwd=ROOT, capture_output=True, text=True)
    assert tracked.stdout.split() == [], "tracked files match the ignore patterns"
