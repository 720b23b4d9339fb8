"""Operator commands of userctl: what the fleet looks like and telling it what to do.

userctl robots ls [--all] [--json]            robots, their agent, state, episodes (Control.ListRobots)
userctl robots forget ROBOT                   drop an offline robot for good: record, episode history, totals
                                              (its experiments keep its episodes in their totals)
userctl workers ls [--all] [--json]           learner/inference hosts with CPUs and GPUs (Control.ListWorkers)
userctl command pause|resume|reset [ROBOT]    send a command and print each edge's result
userctl exp ls [--json]                       experiments: state (failed when the learner cannot train it), leased
                                              robots, episodes, success (without human help)
userctl exp start|stop NAME                   lease its robots again / release them (edges hold, learner pauses)
userctl exp status NAME [--json]              one experiment: its robots, episodes, success, returns, version
userctl exp define FILE                       a new experiment while the stack runs (one `experiments` entry,
                                              YAML or JSON); it takes robots no earlier selector picks
userctl exp remove NAME                       take away a stopped experiment that `define` added (its name
                                              stays taken: episodes, checkpoint and replay table keep it)
userctl edge discover [--sim KIND ...]        probe cameras and serial ports, print a ready edge config
userctl edge install-service [--dry-run]      systemd unit for the edge daemon on this robot PC

The control address is --control, else the control of a `userctl up` running this config's run dir, else
edge.control_addr; the token is auth.* as usual, else that run's generated token (user.up.ops_target).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import grpc
import yaml
from google.protobuf.json_format import MessageToDict
from rich.console import Console
from rich.table import Table

from user.config import ConfigError, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc

COMMANDS = ("robots", "workers", "command", "exp")


def add_parsers(sub: Any) -> None:
    for name, help_ in [("robots", "list robots, forget one"), ("workers", "list learner and inference workers")]:
        p = sub.add_parser(name, help=help_)
        p.add_argument("action", choices=["ls", "forget"] if name == "robots" else ["ls"])
        if name == "robots":
            p.add_argument("robot", nargs="?", default="", help="forget: the robot id (offline)")
        p.add_argument("--all", action="store_true", help="include offline ones")
        p.add_argument("--json", action="store_true", help="one JSON document instead of a table")
        _common(p)
    p = sub.add_parser("command", help="send pause/resume/reset to a robot (or every robot)")
    p.add_argument("kind", choices=["pause", "resume", "reset"])
    p.add_argument("robot", nargs="?", default="", help="robot id; omitted = every robot of every live agent")
    p.add_argument("--wait", type=float, default=5.0, help="seconds to wait for the edges' results")
    _common(p)
    p = sub.add_parser("exp", help="experiments: ls | start NAME | stop NAME | status NAME | define FILE | remove NAME")
    p.add_argument("action", choices=["ls", "start", "stop", "status", "define", "remove"])
    p.add_argument(
        "name", nargs="?", default="", help="experiment name (start, stop, status, remove); define: a YAML/JSON file"
    )
    p.add_argument("--json", action="store_true", help="one JSON document instead of a table")
    _common(p)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", help="stack YAML (configs/)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    p.add_argument("--control", help="control address HOST:PORT (default: edge.control_addr)")
    p.add_argument("--timeout", type=float, default=10.0)


def _ago(ns: int) -> str:
    if ns <= 0:
        return "-"
    s = max(0.0, time.time() - ns / 1e9)
    return f"{s:.0f}s ago" if s < 120 else f"{s / 60:.0f}m ago" if s < 7200 else f"{s / 3600:.1f}h ago"


def _gib(n: int) -> str:
    return f"{n / 2**30:.1f} GiB"


def robots_table(robots: list[control_pb2.RobotInfo]) -> Table:
    # Episodes and successes are control's stored totals for the robot (all experiments, across restarts), helped
    # or not (`exp status` counts success without human help); steps and rates are the edge's own counters.
    table = Table(
        "robot",
        "kind",
        "agent",
        "host",
        "state",
        "lease",
        "episodes",
        "success (all)",
        "steps/s",
        "policy",
        "last beat",
        caption="success (all): every episode, those a teleoperator helped included; exp status counts unhelped ones",
    )
    for r in robots:
        st = r.status
        state = control_pb2.RobotState.Name(st.state).removeprefix("ROBOT_STATE_").lower() if r.online else "offline"
        rate = f"{st.successes / st.episodes:.0%}" if st.episodes else "-"
        table.add_row(
            r.spec.robot_id,
            r.spec.kind,
            r.agent_id,
            r.hostname,
            state,
            _lease(r),
            str(st.episodes),
            rate,
            f"{st.env_steps_per_s:.1f}",
            str(st.policy_version),
            _ago(r.last_heartbeat_ns),
        )
    return table


def _lease(r: control_pb2.RobotInfo) -> str:
    if r.lease:
        return r.lease
    if r.lease_reason:
        return f"held ({r.lease_reason})"
    return "-"


def _state(e: control_pb2.ExperimentInfo) -> str:
    """Control's state, unless a learner reports it cannot train the experiment: control still leases its
    robots then, but "running" would be false (why: ExperimentInfo.learner_error, shown by `exp status`)."""
    state = control_pb2.ExperimentState.Name(e.state).removeprefix("EXPERIMENT_STATE_").lower()
    if not e.learner_failed:
        return state
    return "failed (learner)" if e.state == control_pb2.EXPERIMENT_STATE_RUNNING else f"{state}, failed (learner)"


def _rate(successes: int, episodes: int) -> str:
    return f"{successes / episodes:.0%}" if episodes else "-"


def _success(e: control_pb2.ExperimentInfo) -> str:
    """Success over the episodes nobody intervened in (an expert's rescue is not the policy's success), with
    the rate over every episode in brackets when some were helped: "-" when all were."""
    cell = _rate(e.unhelped_successes, e.unhelped_episodes)
    if e.unhelped_episodes != e.episodes:
        cell += f" [{_rate(e.successes, e.episodes)} all]"
    return cell


def experiments_table(experiments: list[control_pb2.ExperimentInfo]) -> Table:
    table = Table(
        "experiment",
        "state",
        "leased",
        "max",
        "episodes",
        "success",
        "mean return",
        "policy",
        "since",
        caption="success: episodes without human help (in brackets: every episode's, when some were helped)",
    )
    for e in experiments:
        since = e.started_at_ns if e.state == control_pb2.EXPERIMENT_STATE_RUNNING else e.stopped_at_ns
        table.add_row(
            e.name + (" (defined)" if e.defined_at_runtime else ""),
            _state(e),
            str(len(e.leased_robots)),
            str(e.max_robots or "all"),
            str(e.episodes),
            _success(e),
            f"{e.mean_return:.2f}" if e.episodes else "-",
            str(e.policy_version),
            _ago(since),
        )
    return table


def experiment_text(e: control_pb2.ExperimentInfo) -> str:
    """`exp status`: a header and one line per robot (stable columns, for people and grep)."""
    helped = e.episodes - e.unhelped_episodes
    lines = [
        f"experiment {e.name}: {_state(e)}",
        *([f"  learner error: {e.learner_error}"] if e.learner_failed else []),
        f"  started {_ago(e.started_at_ns)}; stopped {_ago(e.stopped_at_ns)}; max_robots {e.max_robots or 'all'}",
        f"  leased {len(e.leased_robots)}: {', '.join(e.leased_robots) or '-'}",
        f"  episodes {e.episodes}{f' ({helped} with interventions)' if helped else ''}, success {_success(e)}, "
        f"mean return {e.mean_return:.2f}, policy version {e.policy_version}",
        f"  learners: {', '.join(e.learners) or '-'}",
        f"  {'robot':<24} {'online':<7} {'leased':<7} {'episodes':>8} {'success':>8} {'return':>8} {'policy':>7}"
        f" {'helped':>7}",
    ]
    for r in e.robots:
        lines.append(
            f"  {r.robot_id:<24} {'yes' if r.online else 'no':<7} {'yes' if r.leased else 'no':<7} "
            f"{r.episodes:>8} {_rate(r.unhelped_successes, r.unhelped_episodes):>8} {r.mean_return:>8.2f} "
            f"{r.policy_version:>7} {r.episodes - r.unhelped_episodes:>7}"
        )
    held = [f"    {r.robot_id}: {r.hold_reason}" for r in e.robots if r.hold_reason]
    if held:
        lines += [f"  held {len(held)} (online, selected, not acting):", *held]
    lines.append(
        "  success: episodes no teleoperator helped in (every episode's rate in brackets; helped = the others)"
    )
    return "\n".join(lines)


def _exp(args: argparse.Namespace, stub: control_pb2_grpc.ControlStub, out: Console) -> int:
    if args.action == "ls":
        resp = stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=args.timeout)
        if args.json:
            print(json.dumps(MessageToDict(resp), indent=1))
        else:
            out.print(experiments_table(list(resp.experiments)))
        return 0
    if not args.name:
        print(f"userctl exp {args.action}: name the experiment (userctl exp ls lists them)", file=sys.stderr)
        return 2
    if args.action == "define":
        try:
            definition = yaml.safe_load(Path(args.name).read_text())
        except (OSError, yaml.YAMLError) as exc:
            print(f"userctl exp define: cannot read {args.name}: {exc}", file=sys.stderr)
            return 2
        request = control_pb2.DefineExperimentRequest(definition_json=json.dumps(definition, default=str))
        info = stub.DefineExperiment(request, timeout=args.timeout)
    elif args.action == "status":
        info = stub.GetExperiment(control_pb2.GetExperimentRequest(name=args.name), timeout=args.timeout)
    elif args.action == "start":
        info = stub.StartExperiment(control_pb2.StartExperimentRequest(name=args.name), timeout=args.timeout)
    elif args.action == "remove":
        info = stub.RemoveExperiment(control_pb2.RemoveExperimentRequest(name=args.name), timeout=args.timeout)
        if args.json:
            print(json.dumps(MessageToDict(info), indent=1))
        else:
            print(f"experiment {info.name} removed ({info.episodes} episodes kept in control's history)")
        return 0
    else:
        info = stub.StopExperiment(control_pb2.StopExperimentRequest(name=args.name), timeout=args.timeout)
    if args.json:
        print(json.dumps(MessageToDict(info), indent=1))
    elif args.action == "status":
        print(experiment_text(info))
    else:
        defined = " (defined)" if args.action == "define" else ""
        print(f"experiment {info.name}{defined}: {_state(info)}; leased {', '.join(info.leased_robots) or '-'}")
    if args.action == "define":
        _warn_if_shadowed(stub, info.name, args.timeout)
    return 0


def _forget(args: argparse.Namespace, stub: control_pb2_grpc.ControlStub) -> int:
    if not args.robot:
        print("userctl robots forget: name the robot (userctl robots ls --all lists them)", file=sys.stderr)
        return 2
    resp = stub.ForgetRobot(control_pb2.ForgetRobotRequest(robot_id=args.robot), timeout=args.timeout)
    print(f"robot {resp.robot_id} forgotten ({resp.episodes} episodes stay counted in their experiments' totals)")
    return 0


def _warn_if_shadowed(stub: control_pb2_grpc.ControlStub, name: str, timeout: float) -> None:
    """Say so when an earlier experiment selects every robot the new one selects (first match wins)."""
    from user.config import ExperimentConfig
    from user.experiments import shadowed

    listed = stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=timeout).experiments
    first = shadowed([ExperimentConfig.model_validate_json(e.definition_json) for e in listed]).get(name)
    if first is not None:
        print(
            f"note: experiment {first} comes first and selects every robot {name} selects, so {name} gets none "
            f"while {first} exists (stopping {first} holds its robots; it does not hand them on)",
            file=sys.stderr,
        )


def workers_table(workers: list[control_pb2.WorkerInfo]) -> Table:
    table = Table("worker", "kind", "address", "device", "CPUs", "GPUs", "serves", "online", "last seen")
    for w in workers:
        gpus = [d for d in w.devices if d.name.startswith("cuda")]
        gpu_text = ", ".join(f"{d.name} {d.model} {_gib(d.memory_bytes)}" for d in gpus) or "-"
        table.add_row(
            w.worker_id,
            w.kind,
            w.address,
            w.device,
            str(w.cpu_count),
            gpu_text,
            ", ".join(w.experiments) or "-",
            "yes" if w.online else "no",
            _ago(w.last_seen_ns),
        )
    return table


def main(args: argparse.Namespace, cfg: StackConfig) -> int:
    from user.up import ops_target

    try:
        target, auth = ops_target(cfg, args.control)
        channel = make_channel(target, auth)
    except (ConfigError, OSError) as exc:  # no token anywhere, an unreadable token or TLS file: say so, no traceback
        print(f"userctl {args.command}: {exc}", file=sys.stderr)
        return 2
    out = Console(width=160)
    with channel:
        stub = control_pb2_grpc.ControlStub(channel)
        try:
            if args.command == "robots" and args.action == "forget":
                return _forget(args, stub)
            if args.command == "robots" and args.robot:
                print(f"userctl robots ls: takes no robot id, got {args.robot!r} (forget takes one)", file=sys.stderr)
                return 2
            if args.command == "robots":
                robots = stub.ListRobots(control_pb2.ListRobotsRequest(include_offline=args.all), timeout=args.timeout)
                if args.json:
                    print(json.dumps(MessageToDict(robots), indent=1))
                else:
                    out.print(robots_table(list(robots.robots)))
            elif args.command == "exp":
                return _exp(args, stub, out)
            elif args.command == "workers":
                workers = stub.ListWorkers(
                    control_pb2.ListWorkersRequest(include_offline=args.all), timeout=args.timeout
                )
                if args.json:
                    print(json.dumps(MessageToDict(workers), indent=1))
                else:
                    out.print(workers_table(list(workers.workers)))
            else:
                kind = control_pb2.CommandKind.Value(f"COMMAND_KIND_{args.kind.upper()}")
                req = control_pb2.SendCommandRequest(
                    command=control_pb2.Command(kind=kind, robot_id=args.robot), wait_result_s=args.wait
                )
                resp = stub.SendCommand(req, timeout=args.timeout + args.wait)
                print(f"command {resp.command_id}: queued for {', '.join(resp.agents) or 'no live agent'}")
                for res in resp.results:
                    print(f"  {res.agent_id}: {'ok' if res.ok else 'FAILED'} {res.message}".rstrip())
                missing = set(resp.agents) - {r.agent_id for r in resp.results}
                for agent in sorted(missing):
                    print(f"  {agent}: no result within {args.wait}s")
                return 0 if resp.agents and all(r.ok for r in resp.results) and not missing else 1
        except grpc.RpcError as err:
            print(f"userctl {args.command}: {target}: {err.code().name}: {err.details()}", file=sys.stderr)
            return 1
    return 0
