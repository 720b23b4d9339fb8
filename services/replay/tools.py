"""`userctl replay ls|export|import`: look into a replay buffer, LeRobotDataset out and in.

  userctl replay ls [--path P | --config C] [--json]
  userctl replay export OUT --repo-id local/name [--table T] [--robot R] [--episodes A:B|N] [--task TEXT] [--fps F]
  userctl replay import DATASET_ROOT --repo-id local/name [--table demos] [--robot-id R]

The buffer is --path if given, else replay.path when the config sets it, else, for a config with an
`up` section, where `userctl up` keeps it (up.runs_dir/up.name/replay), else replay.path's default.
ls and export only read (safe while the service runs); import writes, so it refuses a buffer that a
running replay service holds (stop the service, import, start it again), and reports which episodes and
frames were new and which the buffer already had.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from user.arg_types import non_negative_int, positive_float
from user.config import ConfigError, StackConfig, load_config

TOOLS = {
    "ls": "tables, robots, steps and episodes of a replay buffer",
    "export": "episodes of one robot shape as a new LeRobotDataset v3",
    "import": "append a LeRobotDataset's episodes to a table of the buffer",
}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="userctl replay", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    sub = p.add_subparsers(dest="tool", required=True)
    for name, summary in TOOLS.items():
        s = sub.add_parser(name, help=summary, description=summary)
        _add_tool_arguments(s, name)
        s.add_argument("--path", help="the buffer's LMDB directory (overrides the config)")
        s.add_argument("--config", "-c", help="stack YAML: the buffer is replay.path, or up's when it has `up:`")
        s.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    return p


def _add_tool_arguments(s: argparse.ArgumentParser, tool: str) -> None:
    if tool == "ls":
        s.add_argument("--json", action="store_true", help="print JSON instead of a table")
    if tool == "export":
        _add_export_arguments(s)
    if tool == "import":
        s.add_argument("root", metavar="DATASET_ROOT", help="LeRobotDataset root directory")
        s.add_argument("--repo-id", required=True)
        s.add_argument("--table", default="demos")
        s.add_argument("--robot-id", help="robot id the steps are stored under (default: from repo id)")


def _add_export_arguments(s: argparse.ArgumentParser) -> None:
    s.add_argument("out", metavar="OUT", help="dataset root to create (must not exist)")
    s.add_argument("--repo-id", required=True)
    s.add_argument("--table", default="", help="table to export (default: every episode)")
    s.add_argument("--robot", help="only this robot's episodes (needed when robots of different shapes are selected)")
    s.add_argument(
        "--episodes",
        type=_episode_range,
        default=":",
        metavar="A:B|N",
        help="episodes of the table in arrival order, from 0: A:B (A to B-1), A:, :B, or N (just episode N)",
    )
    s.add_argument("--task", default="", help="task text of every frame (default: the robot spec's task, else kind)")
    s.add_argument("--fps", type=positive_float, help="frames per second (default: the robot's control rate)")


def actions_help() -> str:
    """The tools and their own options, for `userctl replay --help` (whose flags are the service's)."""
    lines = ["buffer tools (`userctl replay ACTION --help` for details):"]
    for name, summary in TOOLS.items():
        tool = argparse.ArgumentParser(prog=f"userctl replay {name}", add_help=False, formatter_class=_Unwrapped)
        _add_tool_arguments(tool, name)
        lines += [f"  {name}: {summary}", "    " + tool.format_usage().removeprefix("usage: ").strip()]
    lines.append("  every tool also takes --path DIR, or --config YAML [--set SECTION.FIELD=VALUE], for the buffer")
    return "\n".join(lines)


class _Unwrapped(argparse.HelpFormatter):
    """A usage on one line: argparse's wrapped continuation lines misalign under an indent."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, width=1000)


def _episode_range(text: str) -> tuple[int, int | None]:
    """A:B, A:, :B or : -> (A, B) for the slice [A:B]; N -> just episode N."""
    if ":" not in text:
        first = _episode(text)
        return first, first + 1
    first_text, _, last_text = text.partition(":")
    first = _episode(first_text) if first_text.strip() else 0
    last = _episode(last_text) if last_text.strip() else None
    if last is not None and last <= first:
        raise argparse.ArgumentTypeError(f"range {text!r} holds no episode (B must be above A)")
    return first, last


def _episode(text: str) -> int:
    try:
        return non_negative_int(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"episode numbers start at 0: {exc}") from None


def _buffer_path(path: str | None, cfg: StackConfig) -> Path:
    """--path, else replay.path when the config sets it, else where `userctl up` puts it for a config with `up:`."""
    if path:
        return Path(path)
    if "path" not in cfg.replay.model_fields_set and "up" in cfg.model_fields_set:
        return _up_replay_path(cfg)
    return cfg.replay.path


def _up_replay_path(cfg: StackConfig) -> Path:
    # the rule of user/up.py: run_up's run_dir, and Stack.start_services sets replay.path=<run_dir>/replay
    return cfg.up.runs_dir / cfg.up.name / "replay"


def _missing_hint(path_arg: str | None, path: Path, cfg: StackConfig) -> str:
    if path_arg:
        return ""
    up_path = _up_replay_path(cfg)
    if path != up_path:
        return f" (`userctl up` with this config keeps it in {up_path}; give the buffer's directory with --path)"
    return " (has `userctl up` run with this config yet? or give the buffer's directory with --path)"


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"userctl replay: {exc}", file=sys.stderr)
        return 2
    path = _buffer_path(args.path, cfg)
    if args.tool != "import" and not (path / "data.mdb").exists():
        print(f"userctl replay: no replay buffer at {path}{_missing_hint(args.path, path, cfg)}", file=sys.stderr)
        return 2
    from services.replay.store import BufferHeld

    try:
        if args.tool == "ls":
            return _ls(path, args.json)
        if args.tool == "export":
            from services.replay.lerobot_io import export_dataset

            first, last = args.episodes
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
    except (ValueError, FileNotFoundError, FileExistsError, BufferHeld) as exc:
        print(f"userctl replay {args.tool}: {exc}", file=sys.stderr)
        return 2
    for note in s.notes:
        print(f"userctl replay {args.tool}: note: {note}", file=sys.stderr)
    already = ""
    if s.present_episodes or s.present_frames:
        already = f" (already there, not stored again: {s.present_episodes} episodes, {s.present_frames} frames)"
    print(f"{args.tool}: {s.episodes} episodes, {s.frames} frames -> {s.path}{already}")
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
