"""`make compose-test`: the compose stack, run for real and checked from outside.

Builds the image, brings docker-compose.yml up under its own project name, and checks:
  every service healthy (docker's health status); steps reaching replay (Replay.Stats); the learner's weight
  version advancing (Learner.GetStatus); inference getting them through the shared tmpfs volume (fp32_shm);
  Prometheus scraping every target ("up" in /api/v1/targets);
  then a crash (SIGKILL of the process) of replay and of the learner: both come back by their restart policy,
  nothing an edge had acked is lost (replay's stored steps per robot == the edges' acked counters once the robots
  are paused and their spools are empty: every step reaches replay exactly once), and the weight version keeps
  advancing and never goes back; then `docker kill` of both (docker keeps a killed container down: a manual
  stop), 10 s down while the edges spool, and the operator's `start`: the same checks.
Tears everything down (`down -v`) whatever happened. Prints a table and writes runs/compose/latest.json.

Works with `docker compose` (v2) or Debian's `docker-compose` 1.29, whichever is there. Where public registries
cannot be reached, build the local bases first (deploy/docker/build-base.sh); they are used when present.
Ports are published on a random 127.x.y.z address, so the test does not collide with a stack on 127.0.0.1.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import grpc  # noqa: E402
from google.protobuf.json_format import MessageToDict  # noqa: E402

from user.config import AuthConfig  # noqa: E402
from user.rpc import make_channel  # noqa: E402
from user.v1 import (  # noqa: E402
    control_pb2,
    control_pb2_grpc,
    learner_pb2,
    learner_pb2_grpc,
    replay_pb2,
    replay_pb2_grpc,
)
from user.weight_shm import owner_of  # noqa: E402

LOCAL_BASE, LOCAL_PROMETHEUS = "user-base:trixie", "user-prometheus:trixie"
PUBLIC_BASE = "python:3.12-slim-bookworm"
IMAGE = "user-robot-learning:compose-test"
PROJECT = "usercomposetest"
PORTS = {"control": 50051, "replay": 50052, "learner": 50054, "prometheus": 9090, "edge-0": 9105, "edge-1": 9106}
EDGES = {"edge-0": "arm-0", "edge-1": "arm-1"}  # edge service -> its one robot (docker-compose.yml)


class Failed(Exception):
    pass


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def run(cmd: list[str], env: dict[str, str] | None = None, check: bool = True, quiet: bool = False) -> str:
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if check and out.returncode != 0:
        raise Failed(f"{' '.join(cmd)} exited {out.returncode}:\n{out.stdout[-3000:]}{out.stderr[-3000:]}")
    if not quiet and out.stderr.strip() and out.returncode != 0:
        log(out.stderr.strip()[-500:])
    return out.stdout


def wait_for(what: str, probe: Callable[[], Any], timeout: float, every: float = 2.0) -> tuple[Any, float]:
    """Poll `probe` until it returns something truthy; (that value, seconds waited). Failed after `timeout`."""
    t0, last_err = time.monotonic(), None
    while time.monotonic() - t0 < timeout:
        try:
            value = probe()
            if value:
                return value, time.monotonic() - t0
        except Exception as exc:  # services come and go in this test: keep probing
            last_err = exc
        time.sleep(every)
    raise Failed(f"{what}: not within {timeout:.0f}s (last error: {last_err})")


def compose_cmd() -> list[str]:
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise Failed("neither `docker compose` nor `docker-compose` is installed")


def image_exists(tag: str) -> bool:
    return subprocess.run(["docker", "image", "inspect", tag], capture_output=True).returncode == 0


class Stack:
    def __init__(self, compose: list[str], env: dict[str, str], host: str) -> None:
        self.compose, self.env, self.host = compose, env, host
        auth = AuthConfig(token=env["USER_TOKEN"])
        self.replay = replay_pb2_grpc.ReplayStub(make_channel(f"{host}:{PORTS['replay']}", auth))
        self.learner = learner_pb2_grpc.LearnerStub(make_channel(f"{host}:{PORTS['learner']}", auth))
        self.control = control_pb2_grpc.ControlStub(make_channel(f"{host}:{PORTS['control']}", auth))

    def dc(self, *args: str, check: bool = True) -> str:
        return run([*self.compose, "-p", PROJECT, "-f", "docker-compose.yml", *args], env=self.env, check=check)

    def containers(self) -> dict[str, str]:
        """service -> container id, from the compose labels (the same for both compose versions)."""
        out = run(["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={PROJECT}"])
        ids = out.split()
        if not ids:
            return {}
        fmt = '{{index .Config.Labels "com.docker.compose.service"}} {{.Id}}'
        lines = run(["docker", "inspect", "--format", fmt, *ids]).splitlines()
        return dict(line.split() for line in lines if line.strip())

    def health(self) -> dict[str, str]:
        """service -> health status ("running" for one without a health check)."""
        fmt = (
            '{{index .Config.Labels "com.docker.compose.service"}} {{.State.Status}} '
            "{{if .State.Health}}{{.State.Health.Status}}{{end}}"
        )
        ids = list(self.containers().values())
        out = run(["docker", "inspect", "--format", fmt, *ids]) if ids else ""
        status = {}
        for line in out.splitlines():
            name, state, *health = line.split()
            status[name] = health[0] if health and state == "running" else state
        return status

    def restarts(self, service: str) -> int:
        cid = self.containers()[service]
        return int(run(["docker", "inspect", "--format", "{{.RestartCount}}", cid]).strip())

    def replay_stats(self) -> replay_pb2.StatsResponse:
        return self.replay.Stats(replay_pb2.StatsRequest(), timeout=5)

    def learner_status(self) -> learner_pb2.LearnerStatus:
        return self.learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)

    def edge_metrics(self, service: str) -> dict[str, float]:
        url = f"http://{self.host}:{PORTS[service]}/metrics"
        text = urllib.request.urlopen(url, timeout=5).read().decode()
        out = {}
        for line in text.splitlines():
            if line.startswith(("user_edge_steps_acked_total ", "user_edge_spool_steps ", "user_edge_steps_unacked ")):
                name, value = line.split()
                out[name] = float(value)
        return out

    def prometheus_targets(self) -> list[dict[str, Any]]:
        url = f"http://{self.host}:{PORTS['prometheus']}/api/v1/targets"
        return json.loads(urllib.request.urlopen(url, timeout=5).read())["data"]["activeTargets"]


def all_healthy(stack: Stack, services: list[str]) -> dict[str, str] | None:
    status = stack.health()
    return status if all(status.get(s) == "healthy" for s in services) else None


def rising(probe: Callable[[], int], what: str, timeout: float) -> tuple[int, int, float]:
    """(first, later, seconds): `probe()` went up."""
    first = probe()
    later, took = wait_for(what, lambda: (v := probe()) > first and v, timeout)
    return first, later, took


def check_acked_not_lost(stack: Stack) -> dict[str, Any]:
    """Read the edges' acked counters first, then replay: everything acked must already be stored."""
    acked = {robot: stack.edge_metrics(edge)["user_edge_steps_acked_total"] for edge, robot in EDGES.items()}
    stored = dict(stack.replay_stats().steps_per_robot)
    for robot, n in acked.items():
        if stored.get(robot, 0) < n:
            raise Failed(f"{robot}: edge acked {n:.0f} steps, replay holds {stored.get(robot, 0)}: acked steps lost")
    return {"acked": acked, "stored": stored}


def kill_and_recover(stack: Stack, service: str, timeout: float) -> dict[str, Any]:
    before = stack.restarts(service)
    t0 = time.monotonic()
    # A crash, as docker sees one: SIGKILL to the service process (the child of the init, tini). `docker kill`
    # would not do: docker treats it as a manual stop and cancels the restart policy for that container.
    cid = stack.containers()[service]
    init_pid = run(["docker", "inspect", "--format", "{{.State.Pid}}", cid]).strip()
    child = run(["pgrep", "-P", init_pid]).split()[0]
    os.kill(int(child), signal.SIGKILL)
    log(f"SIGKILL {service} (pid {child} on the host)")
    wait_for(f"{service} restarted", lambda: stack.restarts(service) > before, timeout, every=0.5)
    restarted = time.monotonic() - t0
    wait_for(f"{service} healthy again", lambda: stack.health().get(service) == "healthy", timeout, every=1.0)
    healthy = time.monotonic() - t0
    log(f"{service}: restarted after {restarted:.1f}s, healthy after {healthy:.1f}s")
    return {"restarted_s": round(restarted, 1), "healthy_again_s": round(healthy, 1)}


def versions_after_restart(stack: Stack, version_before: int, what: str, timeout: float) -> list[int]:
    """The weight versions a restarted learner publishes, until they advance; each must be above every version
    published before (0 = nothing published yet by the new process, skipped)."""
    versions: list[int] = []

    def advanced() -> bool:
        v = stack.learner_status().weight_version
        if v:
            versions.append(v)
        return len(versions) > 1 and versions[-1] > versions[0]

    wait_for(f"weight version advancing after {what}", advanced, timeout)
    if min(versions) <= version_before:
        raise Failed(f"weight version {version_before} before {what}, {min(versions)} after: a version was reused")
    if versions != sorted(versions):
        raise Failed(f"weight versions went back after {what}: {versions}")
    return versions


def docker_kill_and_start(stack: Stack, services: list[str], timeout: float) -> dict[str, Any]:
    """`docker kill` (SIGKILL, which docker records as a manual stop: no restart by policy), a pause with the
    services down while the edges keep collecting into their spools, then the operator's `start`."""
    version_before = stack.learner_status().weight_version
    t0 = time.monotonic()
    run(["docker", "kill", *(stack.containers()[s] for s in services)])
    log(f"docker kill {' '.join(services)}")
    wait_for("killed containers down", lambda: all(stack.health().get(s) == "exited" for s in services), timeout)
    time.sleep(10.0)  # the edges spool what they collect meanwhile
    stack.dc("start", *services)
    back = lambda: all(stack.health().get(s) == "healthy" for s in services)  # noqa: E731
    wait_for("killed services healthy again", back, timeout)
    healthy = time.monotonic() - t0
    versions = versions_after_restart(stack, version_before, "docker kill + start", timeout)
    log(f"docker kill + start: healthy after {healthy:.1f}s, weight version {version_before} -> {versions[-1]}")
    return {"healthy_again_s": round(healthy, 1), "version_before": version_before, "versions_after": versions[-1]}


def learner_shm_sessions(stack: Stack) -> int:
    """user_learner_replay_shm_sessions_total from the learner's /metrics (0 before its first, or while it restarts)."""
    try:
        text = urllib.request.urlopen(f"http://{stack.host}:9104/metrics", timeout=5).read().decode()
    except OSError:
        return 0
    for line in text.splitlines():
        if line.startswith("user_learner_replay_shm_sessions_total "):
            return int(float(line.split()[1]))
    return 0


def scenario(stack: Stack, services: list[str], timeout: float) -> dict[str, Any]:
    res: dict[str, Any] = {}
    t0 = time.monotonic()
    stack.dc("up", "-d", "--no-build")
    status, took = wait_for("every service healthy", lambda: all_healthy(stack, services), timeout, every=3.0)
    res["up_to_all_healthy_s"] = round(time.monotonic() - t0, 1)
    res["health"] = status
    log(f"all {len(status)} services healthy after {res['up_to_all_healthy_s']}s: {status}")

    a, b, took = rising(lambda: stack.replay_stats().steps, "steps reaching replay", timeout)
    res["replay_steps_rising"] = {"from": a, "to": b, "within_s": round(took, 1)}
    log(f"replay steps {a} -> {b}")
    a, b, took = rising(lambda: stack.learner_status().weight_version, "weight version advancing", timeout)
    res["weight_version_advancing"] = {"from": a, "to": b, "within_s": round(took, 1)}
    log(f"weight version {a} -> {b}")

    def inference_via_shm() -> str | None:  # the learner proved inference reads the shared tmpfs volume
        subs = stack.learner_status().subscriber_status
        found = [s for s in subs if s.client_id.startswith("inference-")]
        return learner_pb2.WeightEncoding.Name(found[0].encoding) if found and found[0].versions_sent > 1 else None

    encoding, _ = wait_for("inference's weight stream", inference_via_shm, timeout)
    res["inference_weights_encoding"] = encoding
    log(f"inference gets weights as {encoding}")
    if encoding != "WEIGHT_ENCODING_FP32_SHM":
        raise Failed(f"inference gets weights as {encoding}, not through the shared weights-shm volume")

    # the learner proved it shares replay's replay-shm volume (its state-only batches are small: they take the socket)
    sessions, _ = wait_for("a shared-memory session with replay", lambda: learner_shm_sessions(stack) or None, timeout)
    res["learner_replay_shm_sessions"] = sessions
    log(f"learner shared-memory sessions with replay: {sessions}")

    def targets_up() -> list[dict[str, Any]] | None:
        targets = stack.prometheus_targets()
        return targets if targets and all(t["health"] == "up" for t in targets) else None

    targets, took = wait_for("Prometheus scraping every target", targets_up, timeout)
    res["prometheus_targets_up"] = sorted(t["labels"]["instance"] for t in targets)
    log(f"Prometheus: {len(targets)} targets up: {res['prometheus_targets_up']}")

    res["acked_before_kills"] = check_acked_not_lost(stack)

    steps_before = stack.replay_stats().steps
    res["kill_replay"] = kill_and_recover(stack, "replay", timeout)
    res["acked_after_replay_kill"] = check_acked_not_lost(stack)
    a, b, took = rising(lambda: stack.replay_stats().steps, "steps reaching replay after its restart", timeout)
    if a < steps_before:
        raise Failed(f"replay held {steps_before} steps before the kill and {a} after: stored steps lost")
    res["kill_replay"].update(steps_before_kill=steps_before, steps_after_restart=a, steps_rising_to=b)
    # the learner opens a new shared-memory session with the restarted replay (after REOPEN_S), and the killed
    # replay's files are swept by its successor: one replay's files remain
    a, b, _ = rising(lambda: learner_shm_sessions(stack), "a new shared-memory session after the kill", timeout)
    names = stack.dc("exec", "-T", "replay", "ls", "-A", "/data/replay-shm").split()
    owners = sorted({m.group(1) for n in names if (m := re.match(r"\.?user-replay-(\d+-[0-9a-f]{8})", n))})
    res["kill_replay"].update(shm_sessions=[a, b], shm_files_owners=owners)
    if len(owners) != 1:
        raise Failed(f"replay-shm files of {len(owners)} replays after the restart: {names}")

    version_before = stack.learner_status().weight_version
    res["kill_learner"] = kill_and_recover(stack, "learner", timeout)
    versions = versions_after_restart(stack, version_before, "the learner's restart", timeout)
    res["kill_learner"].update(version_before_kill=version_before, versions_after=[versions[0], versions[-1]])
    log(f"weight version {version_before} before the kill, {versions[0]} -> {versions[-1]} after")
    # The killed learner's shared-memory files are swept by its successor (by their free lock: in a restarted
    # container the new learner often has the dead one's pid), not left in RAM: one learner's files remain.
    names = stack.dc("exec", "-T", "learner", "ls", "-A", "/data/weights-shm").split()
    owners = sorted({owner[0] for owner in map(owner_of, names) if owner})
    res["kill_learner"]["shm_files_owners"] = owners
    if len(owners) != 1:
        raise Failed(f"shared-memory files of {len(owners)} learners after the restart: {names}")

    res["docker_kill"] = docker_kill_and_start(stack, ["replay", "learner"], timeout)
    res["acked_after_docker_kill"] = check_acked_not_lost(stack)

    res["final"] = drain_and_compare(stack, timeout)
    targets, _ = wait_for("Prometheus scraping every target after the kills", targets_up, timeout)
    res["prometheus_targets_up_after_kills"] = len(targets)
    return res


def drain_and_compare(stack: Stack, timeout: float) -> dict[str, Any]:
    """Pause every robot, wait until the edges' spools are empty, then replay must hold exactly what was acked."""
    resp = stack.control.SendCommand(
        control_pb2.SendCommandRequest(
            command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id=""), wait_result_s=5
        ),
        timeout=15,
    )
    log(f"pause: {MessageToDict(resp)}")

    def drained() -> dict[str, Any] | None:
        metrics = {edge: stack.edge_metrics(edge) for edge in EDGES}
        if any(m.get("user_edge_steps_unacked", 1) or m.get("user_edge_spool_steps", 0) for m in metrics.values()):
            return None
        stored = dict(stack.replay_stats().steps_per_robot)
        again = {edge: stack.edge_metrics(edge)["user_edge_steps_acked_total"] for edge in EDGES}
        acked = {EDGES[e]: m["user_edge_steps_acked_total"] for e, m in metrics.items()}
        if any(again[e] != metrics[e]["user_edge_steps_acked_total"] for e in EDGES):
            return None  # still moving
        return {"acked": acked, "stored": stored}

    snap, _ = wait_for("edges' spools drained", drained, timeout)
    stats = stack.replay_stats()
    snap["duplicates_deduplicated"] = stats.duplicates
    snap["rejected"] = stats.rejected
    for robot, n in snap["acked"].items():
        if snap["stored"].get(robot, 0) != n:
            raise Failed(f"{robot}: edge acked {n:.0f} distinct steps, replay stores {snap['stored'].get(robot)}")
    log(f"drained: acked {snap['acked']} == stored {snap['stored']}; re-sends deduplicated: {stats.duplicates}")
    return snap


def table(res: dict[str, Any]) -> str:
    rows = [("build image", f"{res.get('build_s', '-')} s")]
    if "up_to_all_healthy_s" in res:
        rows += [
            ("up -> all healthy", f"{res['up_to_all_healthy_s']} s ({len(res['health'])} services)"),
            ("replay steps rising", "{from} -> {to}".format(**res["replay_steps_rising"])),
            ("weight version advancing", "{from} -> {to}".format(**res["weight_version_advancing"])),
            ("inference's weights", res.get("inference_weights_encoding", "-")),
            ("Prometheus targets up", str(len(res["prometheus_targets_up"]))),
        ]
    for svc in ("replay", "learner"):
        k = res.get(f"kill_{svc}")
        if k:
            rows.append((f"SIGKILL {svc}", f"restarted {k['restarted_s']} s, healthy {k['healthy_again_s']} s"))
    if "docker_kill" in res:
        k = res["docker_kill"]
        rows.append(("docker kill replay+learner, start", f"healthy {k['healthy_again_s']} s (10 s down)"))
    if "final" in res:
        f = res["final"]
        rows.append(("acked == stored (per robot)", ", ".join(f"{r} {int(n)}" for r, n in f["acked"].items())))
        rows.append(("re-sends deduplicated", str(f["duplicates_deduplicated"])))
    rows.append(("result", res["result"]))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base-image", default=os.environ.get("BASE_IMAGE"), help="default: user-base:trixie if built")
    ap.add_argument("--prometheus-image", default=os.environ.get("PROMETHEUS_IMAGE"))
    ap.add_argument("--no-build", action="store_true", help=f"reuse {IMAGE}")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds for each wait")
    ap.add_argument("--keep", action="store_true", help="leave the stack running (debugging)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "compose" / "latest.json")
    args = ap.parse_args()

    local = image_exists(LOCAL_BASE)
    base = args.base_image or (LOCAL_BASE if local else PUBLIC_BASE)
    prom = args.prometheus_image or (LOCAL_PROMETHEUS if image_exists(LOCAL_PROMETHEUS) else "prom/prometheus:v3.1.0")
    host = f"127.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(2, 254)}"
    env = {
        **os.environ,
        "USER_TOKEN": secrets.token_hex(16),
        "USER_PUBLISH_HOST": host,
        "USER_IMAGE": IMAGE,
        "BASE_IMAGE": base,
        "PROMETHEUS_IMAGE": prom,
    }
    env.pop("COMPOSE_PROFILES", None)  # Grafana (profile "grafana") is not in Debian's archive: not started here
    compose = compose_cmd()
    stack = Stack(compose, env, host)
    services = [*PORTS, "inference"]
    res: dict[str, Any] = {
        "compose": " ".join(compose) + " " + run([*compose, "version", "--short"], check=False).strip(),
        "docker": run(["docker", "version", "--format", "{{.Server.Version}}"], check=False).strip(),
        "base_image": base,
        "prometheus_image": prom,
        "publish_host": host,
        "load_avg_start": os.getloadavg(),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    log(f"compose: {res['compose']}, base {base}, prometheus {prom}, ports on {host}")
    try:
        stack.dc("down", "-v", "--remove-orphans", check=False)
        if not args.no_build:
            t0 = time.monotonic()
            run(["docker", "build", "--build-arg", f"BASE_IMAGE={base}", "-t", IMAGE, "."], env=env)
            res["build_s"] = round(time.monotonic() - t0, 1)
            log(f"built {IMAGE} in {res['build_s']}s")
        res["image_size"] = run(["docker", "image", "inspect", "--format", "{{.Size}}", IMAGE]).strip()
        res["python"] = run(
            ["docker", "run", "--rm", "--entrypoint", "python", IMAGE, "--version"], check=False
        ).strip()
        res.update(scenario(stack, services, args.timeout))
        res["result"] = "PASS"
    except (Failed, grpc.RpcError) as exc:
        res["result"] = f"FAIL: {exc}"
        log(res["result"])
        log(stack.dc("ps", check=False))
        log(stack.dc("logs", "--tail", "30", check=False)[-6000:])
    finally:
        res["load_avg_end"] = os.getloadavg()
        if not args.keep:
            stack.dc("down", "-v", "--remove-orphans", check=False)
            left = run(["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={PROJECT}"], check=False)
            res["torn_down"] = not left.strip()
            log(f"down -v: {'nothing left' if res['torn_down'] else 'containers left: ' + left}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2, default=str) + "\n")
    print(table(res))
    print(f"wrote {args.out}")
    return 0 if res["result"] == "PASS" else 1


if __name__ == "__main__":
    raise SystemExit(main())
