"""The container deployment, validated without a docker engine: docker-compose.yml, the Dockerfile,
.dockerignore, Prometheus and Grafana provisioning must agree with configs/compose.yaml, with userctl's
command line and with the metric names the code defines."""

from __future__ import annotations

import fnmatch
import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from user import cli
from user.config import AuthConfig, ServerConfig, StackConfig, load_config
from user.rpc import start_server

ROOT = Path(__file__).resolve().parents[1]
APP = "/app"  # WORKDIR of the image; the repo is copied there
CONFIG_IN_IMAGE = f"{APP}/configs/compose.yaml"
SERVERS = ("control", "replay", "inference", "learner")  # compose service name == config section
EDGES = ("edge-0", "edge-1")
USER_SERVICES = (*SERVERS, *EDGES)
SOURCE_DIRS = ("user", "services", "cloud_learner", "edge_agent")


@pytest.fixture(autouse=True)
def _no_env_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    for key in list(os.environ):
        if key.startswith("USER__"):
            monkeypatch.delenv(key)


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


@pytest.fixture(scope="module")
def services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return compose["services"]


@pytest.fixture(scope="module")
def cfg() -> StackConfig:
    return load_config(ROOT / "configs" / "compose.yaml", environ={})


def _section(name: str) -> str:
    return "edge" if name.startswith("edge-") else name


def _env(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: str(v) for k, v in env.items()}


def _edge_cfg(service: dict[str, Any]) -> StackConfig:
    """The config an edge container really runs with: the file plus its USER__ environment."""
    env = {k: v for k, v in _env(service).items() if k.startswith("USER__")}
    return load_config(ROOT / "configs" / "compose.yaml", environ=env)


def _ports(service: dict[str, Any]) -> list[tuple[int, int]]:
    """(host, container) pairs of the short "[IP:]HOST:CONTAINER" syntax; every port is published on a fixed one."""
    out = []
    for spec in service.get("ports", []):
        parts = str(spec).split(":")
        assert len(parts) >= 2, f"port {spec!r} is not published on a fixed host port"
        out.append((int(parts[-2]), int(parts[-1].split("/")[0])))
    return out


def _volumes(service: dict[str, Any]) -> list[tuple[str, str]]:
    out = []
    for spec in service.get("volumes", []):
        source, target = str(spec).split(":")[:2]
        out.append((source, target))
    return out


def _addr_fields(section: Any) -> dict[str, str]:
    return {name: value for name, value in section if name.endswith("_addr")}


# --------------------------------------------------------------------------- services and image


def test_the_user_services_are_exactly_the_five_organs(services: dict[str, dict[str, Any]]) -> None:
    built = {name for name, svc in services.items() if "build" in svc}
    assert built == set(USER_SERVICES)
    assert {"prometheus", "grafana"} <= set(services)


def test_one_image_from_the_one_dockerfile(services: dict[str, dict[str, Any]]) -> None:
    images = {services[name]["image"] for name in USER_SERVICES}
    builds = {json.dumps(services[name]["build"], sort_keys=True) for name in USER_SERVICES}
    assert len(images) == 1, images
    assert len(builds) == 1, builds
    build = services["control"]["build"]
    assert build["context"] == "."
    assert (ROOT / build.get("dockerfile", "Dockerfile")).is_file()


def test_every_command_is_a_valid_userctl_command_line(services: dict[str, dict[str, Any]]) -> None:
    parser = cli._parser()
    for name in USER_SERVICES:
        command = services[name]["command"]
        assert isinstance(command, list), f"{name}: use the exec form"
        args = parser.parse_args(command)  # SystemExit on an unknown subcommand or flag
        assert args.command == _section(name), f"{name} runs `userctl {args.command}`"
        assert args.config == CONFIG_IN_IMAGE


def test_the_config_every_service_reads_is_a_repo_file(services: dict[str, dict[str, Any]]) -> None:
    for name in USER_SERVICES:
        mounts = {t: s for s, t in _volumes(services[name])}
        assert mounts.get(CONFIG_IN_IMAGE) == "./configs/compose.yaml", f"{name} must mount configs/compose.yaml"
    assert (ROOT / Path(CONFIG_IN_IMAGE).relative_to(APP)).is_file()


def test_every_bind_mount_source_exists(services: dict[str, dict[str, Any]]) -> None:
    binds = [(name, src) for name, svc in services.items() for src, _ in _volumes(svc) if src.startswith(".")]
    assert binds
    for name, src in binds:
        assert (ROOT / src).exists(), f"{name} mounts {src}, which is not in the repo"


def test_named_volumes_used_and_declared_match(compose: dict[str, Any], services: dict[str, dict[str, Any]]) -> None:
    used = {src for svc in services.values() for src, _ in _volumes(svc) if not src.startswith((".", "/"))}
    declared = set(compose.get("volumes") or {})
    assert used == declared
    state = {"control-data", "replay-data", "checkpoints", "prometheus-data", "grafana-data"}
    assert state | {f"{edge}-spool" for edge in EDGES} | {"weights-shm", "replay-shm"} == declared


def test_learner_and_inference_share_a_tmpfs_volume_as_their_weights_shm_dir(
    compose: dict[str, Any], services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    """A container's /dev/shm is its own: shared-memory weight versions need one tmpfs both mount, at the
    directory both are configured to use (the learner still proves the sharing per stream)."""
    assert cfg.learner.weights_shm_dir == cfg.inference.weights_shm_dir == "/data/weights-shm"
    for name in ("learner", "inference"):
        mounts = {t: s for s, t in _volumes(services[name])}
        assert mounts.get(cfg.learner.weights_shm_dir) == "weights-shm", name
    opts = compose["volumes"]["weights-shm"]["driver_opts"]
    assert opts["type"] == "tmpfs" and "mode=1777" in opts["o"]  # RAM; the non-root user writes there


def test_replay_and_learner_share_a_tmpfs_volume_for_sample_batches(
    compose: dict[str, Any], services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    """Replay writes sample batches as slot files the learner copies out (it proves the sharing per session)."""
    assert cfg.replay.shm_dir == cfg.learner.replay_shm_dir == "/data/replay-shm"
    for name in ("replay", "learner"):
        mounts = {t: s for s, t in _volumes(services[name])}
        assert mounts.get(cfg.replay.shm_dir) == "replay-shm", name
    opts = compose["volumes"]["replay-shm"]["driver_opts"]
    assert opts["type"] == "tmpfs" and "mode=1777" in opts["o"]


def test_state_lives_on_the_named_volumes(services: dict[str, dict[str, Any]], cfg: StackConfig) -> None:
    control_mounts = {t: s for s, t in _volumes(services["control"])}
    assert cfg.control.state_path is not None
    assert control_mounts.get(str(cfg.control.state_path.parent)) == "control-data"
    replay_mounts = {t: s for s, t in _volumes(services["replay"])}
    learner_mounts = {t: s for s, t in _volumes(services["learner"])}
    assert replay_mounts.get(str(cfg.replay.path)) == "replay-data"
    assert learner_mounts.get(str(cfg.learner.checkpoint_dir)) == "checkpoints"


def test_edges_spool_where_the_image_lets_them_write(services: dict[str, dict[str, Any]]) -> None:
    dockerfile = (ROOT / "Dockerfile").read_text()
    for name in EDGES:
        spool = _edge_cfg(services[name]).edge.spool_dir
        assert spool is not None and spool.is_absolute(), f"{name}: spool_dir {spool} (relative: under root-owned /app)"
        assert f" {spool} " in dockerfile or f" {spool}\n" in dockerfile, f"{name}: the Dockerfile must create {spool}"
        # its own named volume: unacked steps outlive the container (`docker compose down`, a new image), and two
        # agents never share one outbox
        mounts = {t: s for s, t in _volumes(services[name])}
        assert mounts.get(str(spool)) == f"{name}-spool", f"{name}: spool {spool} is not on its own volume"


def test_token_comes_from_the_environment_and_is_required(
    services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    assert cfg.auth.enabled and cfg.auth.token is None and cfg.auth.token_file is None
    for name in USER_SERVICES:
        token = _env(services[name]).get("USER_TOKEN", "")
        assert re.fullmatch(r"\$\{USER_TOKEN:\?[^}]+\}", token), f"{name}: USER_TOKEN={token!r}"


# --------------------------------------------------------------------------- network


def test_servers_bind_all_interfaces_and_publish_their_config_ports(
    services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    for name in SERVERS:
        server = getattr(cfg, name).server
        assert server.host == "0.0.0.0", f"{name} must bind 0.0.0.0 in a container"
        ports = _ports(services[name])
        assert sorted(c for _, c in ports) == sorted([server.port, server.metrics_port]), name
        assert all(h == c for h, c in ports), f"{name}: host and container ports differ"


def test_edges_publish_their_metrics_port_on_distinct_host_ports(
    services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    assert cfg.edge.metrics_host == "0.0.0.0"
    for name in EDGES:
        assert [c for _, c in _ports(services[name])] == [_edge_cfg(services[name]).edge.metrics_port]
    hosts = [h for svc in services.values() for h, _ in _ports(svc)]
    assert len(hosts) == len(set(hosts)), f"a host port is published twice: {sorted(hosts)}"


def test_addresses_name_compose_services_and_their_grpc_ports(cfg: StackConfig) -> None:
    grpc_port = {name: getattr(cfg, name).server.port for name in SERVERS}
    for section in ("replay", "inference", "learner", "edge"):
        fields = _addr_fields(getattr(cfg, section))
        assert fields, section
        for field, addr in fields.items():
            host, port = addr.rsplit(":", 1)
            assert host in grpc_port, f"{section}.{field}={addr}: not a compose service"
            assert int(port) == grpc_port[host], f"{section}.{field}={addr}: {host} serves on {grpc_port[host]}"


def test_services_wait_for_what_they_call(services: dict[str, dict[str, Any]], cfg: StackConfig) -> None:
    for name in (*SERVERS, *EDGES):
        section = getattr(cfg, _section(name))
        needs = {addr.rsplit(":", 1)[0] for addr in _addr_fields(section).values()}
        depends = services[name].get("depends_on") or {}
        for dep in needs:
            assert dep in depends, f"{name} calls {dep} but does not depend on it"
            assert depends[dep]["condition"] == "service_healthy", f"{name} -> {dep}"
            assert "healthcheck" in services[dep], f"{name} waits for {dep}, which has no healthcheck"


def test_dependencies_have_no_cycle(services: dict[str, dict[str, Any]]) -> None:
    done: set[str] = set()

    def visit(name: str, path: tuple[str, ...]) -> None:
        assert name not in path, f"depends_on cycle: {' -> '.join((*path, name))}"
        if name in done:
            return
        for dep in services[name].get("depends_on") or {}:
            assert dep in services, f"{name} depends on unknown service {dep}"
            visit(dep, (*path, name))
        done.add(name)

    for name in services:
        visit(name, ())


# --------------------------------------------------------------------------- health checks


def test_every_server_has_a_userctl_health_check_on_its_grpc_port(
    services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    parser = cli._parser()
    for name in SERVERS:
        test = services[name]["healthcheck"]["test"]
        assert test[:2] == ["CMD", "userctl"], f"{name}: {test}"
        args = parser.parse_args(test[2:])
        assert args.command == "health"
        assert args.targets == [f"127.0.0.1:{getattr(cfg, name).server.port}"]
        assert args.config == CONFIG_IN_IMAGE


def test_every_edge_has_a_health_check_on_its_metrics_port(
    services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    for name in EDGES:
        test = services[name]["healthcheck"]["test"]
        assert f"127.0.0.1:{cfg.edge.metrics_port}/metrics" in " ".join(test), f"{name}: {test}"


def test_userctl_health_answers_for_a_real_server(monkeypatch: pytest.MonkeyPatch) -> None:
    """The health check command as compose runs it: exit 0 on SERVING, exempt from the token, 1 when down."""
    running = start_server(
        "health-probe",
        lambda _server: None,
        [],
        ServerConfig(port=0),
        AuthConfig(token="test-token"),
        start_metrics=False,
    )
    target = f"127.0.0.1:{running.port}"
    argv = ["health", target, "-c", str(ROOT / "configs" / "compose.yaml"), "--timeout", "2"]
    try:
        monkeypatch.setenv("USER_TOKEN", "test-token")
        assert cli.main(argv) == 0
        monkeypatch.setenv("USER_TOKEN", "another-token")  # health is open: a stale token still works
        assert cli.main(argv) == 0
    finally:
        running.stop()
    assert cli.main(argv) == 1


# --------------------------------------------------------------------------- edge agents


def test_edge_agents_differ_in_agent_and_robot_ids(services: dict[str, dict[str, Any]]) -> None:
    cfgs = {name: _edge_cfg(services[name]) for name in EDGES}
    agent_ids = [c.edge.agent_id for c in cfgs.values()]
    robot_ids = [r.id for c in cfgs.values() for r in c.edge.robots]
    seeds = [c.edge.seed for c in cfgs.values()]
    assert agent_ids == list(EDGES)
    assert len(robot_ids) == len(set(robot_ids)) == len(EDGES)
    assert len(set(seeds)) == len(EDGES), "edges with one seed would explore identically"
    learner_kind = load_config(ROOT / "configs" / "compose.yaml", environ={}).learner.robot_kind
    assert {r.kind for c in cfgs.values() for r in c.edge.robots} == {learner_kind}


# --------------------------------------------------------------------------- prometheus and grafana


def test_prometheus_scrapes_exactly_the_user_metrics_ports(
    services: dict[str, dict[str, Any]], cfg: StackConfig
) -> None:
    prom = yaml.safe_load((ROOT / "deploy" / "prometheus.yml").read_text())
    targets = {
        target
        for job in prom["scrape_configs"]
        if job["job_name"] != "prometheus"
        for static in job["static_configs"]
        for target in static["targets"]
    }
    expected = {f"{name}:{getattr(cfg, name).server.metrics_port}" for name in SERVERS}
    expected |= {f"{name}:{_edge_cfg(services[name]).edge.metrics_port}" for name in EDGES}
    assert targets == expected
    mounts = {t: s for s, t in _volumes(services["prometheus"])}
    config_flag = next(a for a in services["prometheus"]["command"] if a.startswith("--config.file="))
    assert mounts[config_flag.split("=", 1)[1]] == "./deploy/prometheus.yml"


def test_grafana_is_provisioned_with_prometheus_and_the_dashboard(services: dict[str, dict[str, Any]]) -> None:
    grafana = services["grafana"]
    mounts = {s: t for s, t in _volumes(grafana)}
    prov = ROOT / "deploy" / "grafana" / "provisioning"
    assert mounts["./deploy/grafana/provisioning"] == "/etc/grafana/provisioning"
    (datasource,) = yaml.safe_load((prov / "datasources" / "prometheus.yml").read_text())["datasources"]
    prom_port = _ports(services["prometheus"])[0][1]
    assert datasource["type"] == "prometheus"
    assert datasource["url"] == f"http://prometheus:{prom_port}"
    (provider,) = yaml.safe_load((prov / "dashboards" / "user.yml").read_text())["providers"]
    assert mounts["./deploy/grafana/dashboards"] == provider["options"]["path"]
    dashboards = list((ROOT / "deploy" / "grafana" / "dashboards").glob("*.json"))
    assert [d.name for d in dashboards] == ["user-stack.json"]
    home = _env(grafana)["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"]
    assert home == f"{provider['options']['path']}/user-stack.json"
    for panel in _panels():
        assert panel["datasource"]["uid"] == datasource["uid"], panel["title"]


def _panels() -> list[dict[str, Any]]:
    dash = json.loads((ROOT / "deploy" / "grafana" / "dashboards" / "user-stack.json").read_text())
    return [p for p in dash["panels"] if p["type"] != "row"]


def _defined_metrics() -> dict[str, str]:
    """name -> prometheus_client type, for every metric object in our code."""
    pattern = re.compile(r"prometheus_client\.(Counter|Gauge|Histogram|Summary)\(\s*\"(user_[a-z0-9_]+)\"")
    found: dict[str, str] = {}
    for folder in SOURCE_DIRS:
        for path in (ROOT / folder).rglob("*.py"):
            if "v1" not in path.parts:
                found.update({name: kind for kind, name in pattern.findall(path.read_text())})
    return found


def test_every_dashboard_metric_is_defined_in_the_code() -> None:
    defined = _defined_metrics()
    assert "user_grpc_server_handled_total" in defined
    used: set[str] = set()
    for panel in _panels():
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            used |= set(re.findall(r"\buser_[a-z0-9_]+", target["expr"]))
    for name in sorted(used):
        base = re.sub(r"_(bucket|sum|count)$", "", name)
        if name in defined:
            continue
        assert defined.get(base) == "Histogram", f"dashboard uses {name}, which no prometheus_client object defines"
    histos = {re.sub(r"_(bucket|sum|count)$", "", n) for n in used}
    required = {
        "user_edge_env_steps_total",  # env steps/s per robot
        "user_edge_episodes_total",  # success episodes
        "user_edge_loop_jitter_seconds",  # loop jitter
        "user_learner_updates_total",  # learner updates/s
        "user_learner_weight_version",
        "user_replay_transitions",
        "user_inference_batch_size",
        "user_inference_compute_seconds",
        "user_grpc_server_handled_total",  # RPC codes
    }
    assert required <= histos, required - histos


# --------------------------------------------------------------------------- Dockerfile and .dockerignore


def _dockerfile() -> list[str]:
    """Instructions with continuation lines joined and comments dropped."""
    lines, current = [], ""
    for raw in (ROOT / "Dockerfile").read_text().splitlines():
        if raw.strip().startswith("#") or not raw.strip():
            continue
        current += raw.rstrip("\\").strip() + " "
        if not raw.rstrip().endswith("\\"):
            lines.append(current.strip())
            current = ""
    return lines


def _protoc_args(text: str) -> list[str]:
    match = re.search(r"-m grpc_tools\.protoc ([^\n&;]*)", text)
    assert match, text
    return [a for a in shlex.split(match.group(1)) if a.startswith("-")]


def test_dockerfile_base_entrypoint_user_and_mujoco(services: dict[str, dict[str, Any]]) -> None:
    lines = _dockerfile()
    arg = re.fullmatch(r"ARG BASE_IMAGE=(\S+)", lines[0])
    assert arg and re.fullmatch(r"python:3\.12-slim(-\w+)?", arg.group(1)), lines[0]
    assert lines[1] == "FROM ${BASE_IMAGE}"
    # compose passes the same default, so `docker compose build` and `docker build` make the same image
    assert services["control"]["build"]["args"]["BASE_IMAGE"] == f"${{BASE_IMAGE:-{arg.group(1)}}}"
    assert lines.count('ENTRYPOINT ["userctl"]') == 1
    users = [line.split()[1] for line in lines if line.startswith("USER ")]
    assert users and users[-1] not in ("root", "0"), "the image must not run as root"
    text = "\n".join(lines)
    for pkg in ("libegl1", "libgl1", "libosmesa6"):
        assert re.search(rf"apt-get install [^&]*\b{pkg}\b", text), pkg
    assert re.search(r"\bMUJOCO_GL=egl\b", text)


def test_dockerfile_installs_dependencies_before_copying_the_code() -> None:
    lines = _dockerfile()
    copies = [i for i, line in enumerate(lines) if line.startswith("COPY ")]
    first, everything = copies[0], next(i for i in copies if lines[i] == "COPY . .")
    assert set(lines[first].split()[1:-1]) == {"pyproject.toml", "constraints.txt"}
    deps = [i for i, line in enumerate(lines) if "pip install -c constraints.txt" in line]
    assert deps and first < deps[0] < everything, "dependencies must be a layer of their own, before COPY . ."


def test_dockerfile_generates_stubs_like_the_makefile() -> None:
    make_args = _protoc_args((ROOT / "Makefile").read_text())
    docker = "\n".join(_dockerfile())
    assert _protoc_args(docker) == make_args
    stubs = docker.index("grpc_tools.protoc")
    assert docker.index("touch user/v1/__init__.py") > stubs
    install = docker.index("pip install --no-deps")
    assert stubs < install, "stubs must exist before the package is installed, or user.v1 is missing from it"
    assert docker.index("COPY . .") < stubs


def test_dockerfile_prepares_the_volume_mount_points(services: dict[str, dict[str, Any]]) -> None:
    docker = "\n".join(_dockerfile())
    for name in ("control", "replay", "learner"):
        for source, target in _volumes(services[name]):
            if not source.startswith("."):
                assert re.search(rf"mkdir -p [^&]*{re.escape(target)}\b", docker), target


def _ignored(path: str, patterns: list[str]) -> bool:
    ignored = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        pat = pattern.lstrip("!").strip("/")
        parts = Path(path).parts
        prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        if any(fnmatch.fnmatch(p, pat) or fnmatch.fnmatch(p, pat.replace("**/", "")) for p in prefixes):
            ignored = not negate
    return ignored


def test_dockerignore_keeps_the_build_inputs_and_drops_local_state() -> None:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    kept = [
        "pyproject.toml",
        "constraints.txt",
        "README.md",  # pyproject's readme: `pip install .` reads it
        "configs/compose.yaml",
        "proto/user/v1/replay.proto",
        "user/cli.py",
        "services/replay/server.py",
        "cloud_learner/server.py",
        "edge_agent/agent.py",
    ]
    for path in kept:
        assert (ROOT / path).exists(), path
        assert not _ignored(path, patterns), f".dockerignore drops {path}"
    for path in (".venv/bin/python", "runs/demo/replay/data.mdb", "user/v1/replay_pb2.py", ".git/HEAD"):
        assert _ignored(path, patterns), f".dockerignore keeps {path}"


# --------------------------------------------------------------------------- both compose versions, local bases

PUBLISH = "${USER_PUBLISH_HOST:-127.0.0.1}:"


def _compose_schema() -> dict[str, Any]:
    """The Compose Specification's JSON schema, as check-jsonschema (a pinned dev dependency) vendors it."""
    from importlib import resources

    vendor = resources.files("check_jsonschema.builtin_schemas.vendor")
    return json.loads(vendor.joinpath("compose-spec.json").read_text())


def test_the_compose_file_follows_the_compose_specification(compose: dict[str, Any]) -> None:
    """What `docker compose` v2 reads: the Compose Specification (Debian ships no v2 plugin to run it here)."""
    import jsonschema

    schema = _compose_schema()
    validator = jsonschema.validators.validator_for(schema)(schema)
    errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(compose)]
    assert not errors, errors
    for path, value in [
        (("replay", "restart_policy"), "always"),
        (("learner", "depends_on"), {"replay": {"condition": "healthy"}}),
    ]:
        broken = json.loads(json.dumps(compose))
        broken["services"][path[0]][path[1]] = value
        assert list(validator.iter_errors(broken)), f"the schema must catch {path}={value}"


def test_the_compose_file_has_nothing_compose_1_29_rejects(compose: dict[str, Any]) -> None:
    assert "name" not in compose, "docker-compose 1.29 rejects a top-level name: (pass -p)"
    assert "version" not in compose, "the Compose Specification has no version key; v2 warns about it"


def _docker_compose_1(*args: str, token: str | None) -> subprocess.CompletedProcess[str]:
    import os

    variables = ("USER_", "COMPOSE_", "BASE_IMAGE", "PROMETHEUS_IMAGE")  # what the file reads: defaults only
    env = {k: v for k, v in os.environ.items() if not k.startswith(variables)}
    if token is not None:
        env["USER_TOKEN"] = token
    return subprocess.run(
        ["docker-compose", "-p", "usertest", "-f", "docker-compose.yml", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="docker-compose (1.29, Debian) not installed")
def test_docker_compose_1_29_parses_and_resolves_the_file() -> None:
    out = _docker_compose_1("config", token="tok")
    assert out.returncode == 0, out.stderr
    resolved = yaml.safe_load(out.stdout)
    assert set(USER_SERVICES) | {"prometheus"} <= set(resolved["services"])
    for name in USER_SERVICES:
        svc = resolved["services"][name]
        assert svc["environment"]["USER_TOKEN"] == "tok"
        assert svc["build"]["args"]["BASE_IMAGE"].startswith("python:3.12-slim")
        assert {str(p).split(":")[0] for p in svc["ports"]} == {"127.0.0.1"}, f"{name} publishes beyond the loopback"
    missing = _docker_compose_1("config", "-q", token=None)
    assert missing.returncode != 0 and "set USER_TOKEN" in missing.stderr


def test_every_port_is_published_on_the_configurable_loopback(services: dict[str, dict[str, Any]]) -> None:
    for name, svc in services.items():
        for spec in svc.get("ports", []):
            assert str(spec).startswith(PUBLISH), f"{name}: {spec} (default must be the loopback)"


def test_grafana_is_opt_in_and_prometheus_image_replaceable(services: dict[str, dict[str, Any]]) -> None:
    assert services["grafana"]["profiles"] == ["grafana"], "Grafana is not in Debian: a profile keeps it optional"
    assert all("profiles" not in services[name] for name in (*USER_SERVICES, "prometheus"))
    prom = services["prometheus"]
    assert re.fullmatch(r"\$\{PROMETHEUS_IMAGE:-prom/prometheus:v[\d.]+\}", prom["image"]), prom["image"]
    assert prom["healthcheck"]["test"][:4] == ["CMD", "promtool", "check", "healthy"]
    assert all(a.startswith("--") for a in prom["command"]), "flags only: both images' entrypoint is prometheus"
    local = (ROOT / "deploy" / "docker" / "prometheus.Dockerfile").read_text()
    assert 'ENTRYPOINT ["/usr/bin/prometheus"]' in local
    assert re.search(r"apt-get install [^&]*\bprometheus\b", local)


def test_the_local_base_script_builds_what_compose_test_uses() -> None:
    script = ROOT / "deploy" / "docker" / "build-base.sh"
    assert script.stat().st_mode & 0o111, "build-base.sh must be executable"
    subprocess.run(["bash", "-n", str(script)], check=True)
    text = script.read_text()
    for pkg in ("python3", "python3-venv", "python3-dev", "gcc", "libc6-dev"):
        assert re.search(rf"--include=[^ ]*\b{pkg}\b", text), pkg
    driver = (ROOT / "deploy" / "compose_test.py").read_text()
    base = re.search(r'LOCAL_BASE, LOCAL_PROMETHEUS = "([^"]+)", "([^"]+)"', driver)
    assert base, "compose_test.py names the local images"
    assert base.group(1) == "user-base:trixie" and "BASE_TAG=${USER_BASE_IMAGE:-user-base:$SUITE}" in text
    assert (
        base.group(2) == "user-prometheus:trixie"
        and "PROM_TAG=${USER_PROMETHEUS_IMAGE:-user-prometheus:$SUITE}" in text
    )
    assert "SUITE=${1:-trixie}" in text
