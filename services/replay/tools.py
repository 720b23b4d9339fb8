"""`userctl replay ls|export|import`: look into a replay buffer, LeRobotDataset out and in.

  userctl replay ls [--path P | --config C] [--json]
  userctl replay export OUT --repo-id local/name [--table T] [--robot R] [--episodes A:B] [--task TEXT]
  userctl replay import DATASET_ROOT --repo-id local/name [--table demos] [--robot-id R]

The buffer is replay.path of the config unless --path is given. ls and export only read (safe while
the service runs); import writes, so run it with the service for that path stopped.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from user.config import ConfigError, load_config


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="userctl replay", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    sub = p.add_subparsers(dest="tool", required=True)
    for name in ("ls", "export", "import"):
        s = sub.add_parser(name)
        s.add_argument("--config", "-c", help="stack YAML: replay.path is the buffer")
        s.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE")
        s.add_argument("--path", help="the buffer's LMDB directory (overrides the config)")
        if name == "ls":
            s.add_argument("--json", action="store_true", help="print JSON instead of a table")
        if name == "export":
            s.add_argument("out", help="dataset root to create (must not exist)")
            s.add_argument("--repo-id", required=True)
            s.add_argument("--table", default="", help="table to export (default: every episode)")
            s.add_argument("--robot", help="only this robot's episodes")
            s.add_argument("--episodes", default=":", help="range A:B of the table's episodes in arrival order")
            s.add_argument("--task", default="", help="task text of every frame (default: the robot kind)")
            s.add_argument("--fps", type=int, help="default: the robot's control rate")
        if name == "import":
            s.add_argument("root", help="LeRobotDataset root directory")
            s.add_argument("--repo-id", required=True)
            s.add_argument("--table", default="demos")
            s.add_argument("--robot-id", help="robot id the steps are stored under (default: from repo id)")
    return p


def _range(text: str) -> tuple[int, int | None]:
    first, _, last = text.partition(":")
    return int(first or 0), (int(last) if last else None)


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"userctl replay: {exc}", file=sys.stderr)
        return 2
    path = Path(args.path) if args.path else Path(cfg.replay.path)
    if args.tool != "import" and not (path / "data.mdb").exists():
        print(f"userctl replay: no replay buffer at {path}", file=sys.stderr)
        return 2
    try:
        if args.tool == "ls":
            return _ls(path, args.json)
        if args.tool == "export":
            from services.replay.lerobot_io import export_dataset

            first, last = _range(args.episodes)
            s = export_dataset(
                path,
                args.out,
                args.repo_id,
                table=args.table,
                robot_id=args.robot,
                first_episode=first,
                last_episode=last,
                task=args.task,
                fps=args.fps,
            )
        else:
            from services.replay.lerobot_io import import_dataset

            s = import_dataset(args.root, args.repo_id, path, table=args.table, robot_id=args.robot_id)
    except (ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"userctl replay {args.tool}: {exc}", file=sys.stderr)
        return 2
    print(f"{args.tool}: {s.episodes} episodes, {s.frames} frames -> {s.path}")
    return 0


def _ls(path: Path, as_json: bool) -> int:
    from rich.console import Console
    from rich.table import Table

    from services.replay.store import ReplayStore

    store = ReplayStore(path, cache_mb=0, readonly=True)
    try:
        stats, tables = store.stats(), store.table_stats()
    finally:
        store.close()
    if as_json:
        print(json.dumps({"path": str(path), **stats, "tables": tables}, indent=2))
        return 0
    out = Table(title=f"replay {path}: {stats['steps']} steps, {stats['bytes_on_disk'] / 2**20:.1f} MiB on disk")
    for col in ("table", "robot", "transitions", "steps", "episodes", "MiB", "success"):
        out.add_column(col, justify="left" if col in ("table", "robot") else "right")
    for name, t in sorted(tables.items()):
        rows = [("(all)", t), *sorted(t["robots"].items())]
        for robot, r in rows:
            out.add_row(
                name if robot == "(all)" else "",
                robot,
                str(r["transitions"]),
                str(r["steps"]),
                str(r["episodes"]),
                f"{r['bytes'] / 2**20:.2f}",
                f"{r['success_rate']:.0%}",
            )
    Console().print(out)
    return 0
