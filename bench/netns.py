"""Run a bench child in a private network namespace whose 127.0.0.1 is a slow link (tc on lo).

The child prints "LOG ..." lines, which are passed on, and its rows as JSON on its last line.
"""

from __future__ import annotations

import json
import subprocess
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
