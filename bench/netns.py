"""Run a bench child in a private network namespace whose 127.0.0.1 is a slow link (tc on lo).

The child prints "LOG ..." lines, which are passed on, and its rows as JSON on its last line.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Callable

from bench import Row


def rows_in_netns(setup: str, cmd: list[str], log: Callable[..., None]) -> tuple[list[Row] | None, str]:
    """(the child's rows, "") or (None, why the namespace or the child failed). `setup` is the shell that makes
    the link (run first inside the namespace), `cmd` the child's argv."""
    shell = f"{setup} && exec {' '.join(cmd)}"
    err = "?"
    for prefix in (["unshare", "-n"], ["unshare", "-rn"]):  # as root, else as a user namespace's root
        try:
            proc = subprocess.run([*prefix, "sh", "-c", shell], capture_output=True, text=True, timeout=900)
        except (OSError, subprocess.TimeoutExpired) as exc:
            err = str(exc)
            continue
        if proc.returncode == 0:
            for line in proc.stdout.splitlines():
                if line.startswith("LOG "):
                    log(line[4:])
            return [Row(**r) for r in json.loads(proc.stdout.strip().splitlines()[-1])], ""
        err = ((proc.stderr or proc.stdout).strip().splitlines() or ["?"])[-1]
    return None, err


def tbf_setup(rate: str, burst: str = "64kb", latency: str = "400ms", mtu: int | None = 1500) -> str:
    """Shell that brings up lo (with a real link's MTU unless mtu is None) behind a tc tbf qdisc at `rate`."""
    mtu_cmd = f" && ip link set lo mtu {mtu}" if mtu else ""
    return f"ip link set lo up{mtu_cmd} && tc qdisc add dev lo root tbf rate {rate} burst {burst} latency {latency}"


SLOW_LINK = tbf_setup("20mbit")  # a remote site's uplink or a busy Wi-Fi: 127.0.0.1 moves ~19 Mbit/s


def link_rows(setup: str, args: list[str], group: str, log: Callable[..., None]) -> list[Row]:
    """The rows of `python -m <args>` run behind the link, or one row of `group` saying why it was skipped."""
    rows, err = rows_in_netns(setup, [sys.executable, "-m", *args], log)
    if rows is not None:
        return rows
    log(f"{group}: skipped ({err})")
    return [Row(group, "skipped", "n/a", "n/a", note=f"could not emulate: {err}")]


def emit_rows(rows: list[Row]) -> None:
    """A child's last line: its rows as JSON, for rows_in_netns."""
    print(json.dumps([r.__dict__ for r in rows]), flush=True)


def child_main(child: Callable[[bool], None], run: Callable[[bool], list[Row]]) -> None:
    """`python -m <bench> --child [--quick]` runs the child (inside the namespace); without --child, the whole
    benchmark (the parent, which starts the child behind the link) and its rows printed."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--child", action="store_true")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.child:
        os.environ.setdefault("MUJOCO_GL", "egl")
        child(args.quick)
    else:
        for row in run(args.quick):
            print(row)
