"""userctl: one entry point for every USER process.

userctl control|replay|inference|learner|edge --config configs/demo.yaml [--set a.b=c] [--ready-file F]
userctl up --config configs/demo.yaml      # the whole stack locally, with a live console
userctl health HOST:PORT                   # exit 0 when SERVING (docker health checks)
userctl robots ls | workers ls | command pause|resume|reset [ROBOT]   # operators (see user/ops_cli.py)
userctl edge discover | edge install-service                         # robot-PC setup (user/edge_setup.py)
"""

from __future__ import annotations

import argparse
import importlib
import sys

from user.config import ConfigError, StackConfig, load_config
from user.log import setup_logging

# Each service module exposes run(cfg: StackConfig, ready_file: str | None) -> int, blocking until SIGTERM/SIGINT.
SERVICES = {
    "control": "services.control.server",
    "replay": "services.replay.server",
    "inference": "services.inference.server",
    "learner": "cloud_learner.server",
    "edge": "edge_agent.agent",
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="userctl", description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in [*SERVICES, "up"]:
        p = sub.add_parser(name, help=f"run the {name}" if name != "up" else "run the whole stack locally")
        p.add_argument("--config", "-c", help="stack YAML (configs/)")
        p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE")
        if name != "up":
            p.add_argument("--ready-file", help="write bound ports here as JSON once serving")
        else:
            p.add_argument("--fresh", action="store_true", help="delete runs/<name> first instead of resuming it")
    h = sub.add_parser("health", help="gRPC health check of HOST:PORT")
    h.add_argument("target")
    h.add_argument("--config", "-c")
    h.add_argument("--set", dest="overrides", action="append", default=[])
    h.add_argument("--timeout", type=float, default=2.0)
    from user import ops_cli

    ops_cli.add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["edge"] and argv[1:2] and argv[1] in ("discover", "install-service"):
        from user import edge_setup  # robot-PC setup commands; `userctl edge -c ...` runs the daemon

        return edge_setup.main(argv[1:])
    args = _parser().parse_args(argv)
    try:
        cfg: StackConfig = load_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"userctl: {exc}", file=sys.stderr)
        return 2
    if args.command == "health":
        from user.rpc import check_health

        auth = cfg.auth
        try:
            auth.resolved_token()
        except ConfigError:  # health checks are exempt from auth: probing needs no token
            auth = auth.model_copy(update={"enabled": False})
        return 0 if check_health(args.target, auth, timeout_s=args.timeout) else 1
    if args.command in ("robots", "workers", "command"):
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
