"""userctl: one entry point for every USER process.

userctl control|replay|inference|learner|edge --config configs/demo.yaml [--set a.b=c] [--ready-file F]
userctl up --config configs/demo.yaml      # the whole stack locally, with a live console
userctl health HOST:PORT [HOST:PORT ...]   # a status line each; exit 0 when all are SERVING (docker health checks)
userctl plugins                            # each kind: `interface kind description`; exit 1 if a plug-in did not load
userctl plugins INTERFACE KIND             # the params that kind takes: name, type, default, description
userctl replay ls|export|import ...        # a replay buffer's tables; LeRobotDataset out and in
userctl reward train --frames DIR --out DIR  # success classifier for the `classifier` task
userctl robots ls | workers ls | command pause|resume|reset [ROBOT]   # operators (see user/ops_cli.py)
userctl exp ls | exp start|stop|status|remove NAME | exp define FILE   # experiments and their leases
userctl edge discover | edge install-service                         # robot-PC setup (user/edge_setup.py)
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import Any

from user import arg_types
from user.config import AuthConfig, ConfigError, StackConfig, load_config
from user.log import setup_logging

# Each service module exposes run(cfg: StackConfig, ready_file: str | None) -> int, blocking until SIGTERM/SIGINT.
SERVICES = {
    "control": "services.control.server",
    "replay": "services.replay.server",
    "inference": "services.inference.server",
    "learner": "cloud_learner.server",
    "edge": "edge_agent.agent",
}
REPLAY_TOOLS = ("ls", "export", "import")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="userctl", description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in [*SERVICES, "up"]:
        p = sub.add_parser(
            name, help=f"run the {name}" if name != "up" else "run the whole stack locally", **_service_help(name)
        )
        p.add_argument("--config", "-c", help="stack YAML (configs/)")
        p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE")
        if name != "up":
            p.add_argument("--ready-file", help="write bound ports here as JSON once serving")
        else:
            p.add_argument("--fresh", action="store_true", help="delete runs/<name> first instead of resuming it")
    plugins = sub.add_parser("plugins", help="list registered robots, tasks, teleoperators, policies, algorithms")
    plugins.add_argument("interface", nargs="?", help="with KIND: the params that kind takes (name type default)")
    plugins.add_argument("kind", nargs="?")
    h = sub.add_parser("health", help="gRPC health check of HOST:PORT (one line each)")
    h.add_argument("targets", nargs="+", metavar="HOST:PORT", type=arg_types.host_port)
    h.add_argument("--config", "-c")
    h.add_argument("--set", dest="overrides", action="append", default=[])
    h.add_argument("--timeout", type=arg_types.positive_float, default=2.0, help="seconds per target")
    reward = sub.add_parser("reward", help="learned rewards").add_subparsers(dest="reward_command", required=True)
    train = reward.add_parser("train", help="train a success classifier from labelled frames (user/reward_model.py)")
    train.add_argument("--frames", required=True, help="folder with success/ and failure/ frames, or an .npz")
    train.add_argument("--out", required=True, help="output folder (model.safetensors + config.json)")
    train.add_argument("--camera", default="camera.front", help="observation key the frames come from")
    train.add_argument("--epochs", type=int, default=30)
    train.add_argument("--batch-size", type=int, default=32)
    train.add_argument("--lr", type=float, default=1e-3)
    train.add_argument("--seed", type=int, default=0)
    from user import ops_cli

    ops_cli.add_parsers(sub)
    return parser


def _service_help(name: str) -> dict[str, Any]:
    """`userctl replay --help` lists the buffer tools beside the service's flags (main() routes them)."""
    if name != "replay":
        return {}
    from services.replay.tools import actions_help

    return {
        "description": f"run the replay service, or a buffer tool: userctl replay {'|'.join(REPLAY_TOOLS)} ...",
        "epilog": actions_help(),
        "formatter_class": argparse.RawTextHelpFormatter,
    }


def _plugins(interface: str | None = None, kind: str | None = None) -> int:
    from user.registry import PluginError, import_errors, params_lines, plugin_lines

    if interface is not None:
        if kind is None:
            print("userctl plugins: give INTERFACE and KIND (e.g. `userctl plugins algorithm sac`)", file=sys.stderr)
            return 2
        try:
            print("\n".join(params_lines(interface, kind)))
        except PluginError as exc:
            print(f"userctl plugins: {exc}", file=sys.stderr)
            return 2
        return 0
    registry_log = logging.getLogger("user.registry")
    level = registry_log.level
    registry_log.setLevel(logging.ERROR)  # its warnings are the lines printed below, once each
    try:
        print("\n".join(sorted(plugin_lines())))
        errors = import_errors()
    finally:
        registry_log.setLevel(level)
    for module, error in sorted(errors.items()):
        print(f"userctl plugins: module {module} not loaded: {error}", file=sys.stderr)
    return 1 if errors else 0  # an installed plug-in that did not load is a failure (CI, install checks)


def _health(targets: list[str], auth: AuthConfig, timeout_s: float) -> int:
    """`HOST:PORT: SERVING` (or NOT_SERVING, or unreachable and why) per target; 1 unless all are SERVING."""
    try:
        auth.resolved_token()
    except ConfigError:  # health checks are exempt from auth: probing needs no token
        auth = auth.model_copy(update={"enabled": False})
    try:
        serving = [_health_line(target, auth, timeout_s) for target in targets]
    except ConfigError as exc:  # e.g. auth.tls_ca unreadable
        print(f"userctl health: {exc}", file=sys.stderr)
        return 2
    return 0 if all(serving) else 1


def _health_line(target: str, auth: AuthConfig, timeout_s: float) -> bool:
    """Prints the target's status line; True when it is SERVING."""
    from grpc import RpcError
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    from user.rpc import make_channel

    with make_channel(target, auth) as channel:
        try:
            resp = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=timeout_s)
        except RpcError as err:
            details = (err.details() or "").strip().splitlines()[:1]  # one line, as docker's health log shows it
            print(f"{target}: unreachable ({': '.join([err.code().name, *details])})")
            return False
    status = health_pb2.HealthCheckResponse.ServingStatus.Name(resp.status)
    print(f"{target}: {status}")
    return resp.status == health_pb2.HealthCheckResponse.SERVING


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) >= 2 and argv[0] == "replay" and argv[1] in REPLAY_TOOLS:  # userctl replay ls|export|import
        from services.replay.tools import main as replay_tools

        return replay_tools(argv[1:])
    if argv[:1] == ["edge"] and argv[1:2] and argv[1] in ("discover", "install-service"):
        from user import edge_setup  # robot-PC setup commands; `userctl edge -c ...` runs the daemon

        return edge_setup.main(argv[1:])
    args = _parser().parse_args(argv)
    if args.command == "plugins":
        return _plugins(args.interface, args.kind)
    if args.command == "reward":
        from user.reward_model import run_cli

        return run_cli(args)
    try:
        cfg: StackConfig = load_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"userctl: {exc}", file=sys.stderr)
        return 2
    if args.command == "health":
        return _health(args.targets, cfg.auth, args.timeout)
    if args.command in ("robots", "workers", "command", "exp"):
        from user import ops_cli

        return ops_cli.main(args, cfg)
    if args.command == "up":
        from user.up import run_up

        return run_up(cfg, args.config, args.overrides, fresh=args.fresh)
    setup_logging(args.command, cfg.log_level, cfg.log_json)
    module = importlib.import_module(SERVICES[args.command])
    try:
        return int(module.run(cfg, args.ready_file) or 0)
    except ConfigError as exc:
        print(f"userctl {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
