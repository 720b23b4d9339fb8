"""Setting up a robot PC: `userctl edge discover` and `userctl edge install-service`.

discover probes what is attached — OpenCV cameras (through lerobot's finder), serial ports of
Feetech/Dynamixel bus adapters (the lerobot arms: SO-100/101, Koch), and the simulated robots this build
knows — and prints an edge config that validates (`userctl edge -c` runs it). `--sim` adds simulators only;
arms found are listed as commented lerobot entries with their port, so nothing is guessed into a broken config.

install-service writes the systemd unit (restart on failure, logs to journald) and enables it. The unit
restarts forever, so what would only crash-loop is refused first: an edge config `userctl edge -c` would
refuse, a token file it names that cannot be read, a placeholder token, a missing --user or --userctl, an
invalid unit name. The token's place is USER_TOKEN=... in /etc/user/edge.env (the unit's EnvironmentFile).
"""

from __future__ import annotations

import argparse
import getpass
import os
import pwd
import re
import shutil
import socket
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:
    from user.config import AuthConfig

# USB bridges the lerobot arms use: Feetech boards (CH340/CH343, STM32 CDC) and Dynamixel's U2D2 (FTDI).
ARM_BRIDGES = {
    ("1a86", "7523"): "CH340 (Feetech bus: SO-100/SO-101)",
    ("1a86", "55d3"): "CH343 (Feetech bus: SO-100/SO-101)",
    ("0483", "5740"): "STM32 CDC (Feetech bus)",
    ("0403", "6014"): "FTDI FT232H (Dynamixel U2D2: Koch)",
    ("0403", "6001"): "FTDI FT232R (Dynamixel)",
}
SERIAL_GLOBS = ("ttyACM*", "ttyUSB*")
# How to add a hardware robot kind by hand, for `--sim KIND` of one (discover only adds simulators).
HARDWARE_EXAMPLES = {
    "lerobot": "{id: arm-0, kind: lerobot, params: {type: so101_follower, config: {port: /dev/ttyACM0}}}",
}
# systemd's unit-name characters (unit_name_is_valid); "@" is left out: a template/instance name would need
# the template unit this command does not write.
UNIT_NAME = re.compile(r"[A-Za-z0-9:_.\\-]+")
UNIT_NAME_MAX = 255  # systemd's limit, ".service" included
# Where a robot PC keeps its token: USER_TOKEN=... here, read by systemd (EnvironmentFile=) as root.
ENV_FILE = "/etc/user/edge.env"
ENV_TOKEN = re.compile(r"\s*USER_TOKEN\s*=\s*['\"]?([^'\"\s]*)")


@dataclass
class SerialPort:
    device: str
    vid: str = ""
    pid: str = ""
    description: str = ""

    @property
    def arm_bridge(self) -> str | None:
        return ARM_BRIDGES.get((self.vid, self.pid))


def find_serial_ports(dev: Path = Path("/dev"), sys_class: Path = Path("/sys/class/tty")) -> list[SerialPort]:
    """USB serial ports with their vendor/product ids from sysfs (no pyserial needed)."""
    ports = []
    for pattern in SERIAL_GLOBS:
        for path in sorted(dev.glob(pattern)):
            port = SerialPort(str(path))
            usb = (sys_class / path.name / "device").resolve()
            for parent in [usb, *usb.parents][:4]:  # interface -> device directory holds idVendor
                vid, pid = parent / "idVendor", parent / "idProduct"
                if vid.exists() and pid.exists():
                    port.vid, port.pid = vid.read_text().strip(), pid.read_text().strip()
                    product = parent / "product"
                    port.description = product.read_text().strip() if product.exists() else ""
                    break
            ports.append(port)
    return ports


def find_cameras() -> list[dict[str, Any]]:
    """OpenCV cameras with their default width/height/fps (lerobot's finder opens each one)."""
    try:
        from lerobot.cameras.opencv import OpenCVCamera

        return list(OpenCVCamera.find_cameras())
    except Exception as exc:  # no OpenCV backend, no permission: report none rather than fail
        print(f"# cameras: probe failed: {exc}", file=sys.stderr)
        return []


def _sim_refusal(kind: str) -> str:
    """Why `--sim kind` cannot add a bare `{id, kind}` entry (a hardware robot, or params it needs), or ""."""
    from edge_agent.robot import ROBOTS, Robot
    from user.registry import PluginError

    if ROBOTS.get(kind).cls.connect is not Robot.connect:  # connect opens hardware; sims are ready when built
        example = f", e.g. {HARDWARE_EXAMPLES[kind]}" if kind in HARDWARE_EXAMPLES else ""
        return (
            f"{kind} drives real hardware, not a simulator: add it to edge.robots by hand{example} "
            f"(`userctl plugins robot {kind}` lists its params; discover without --sim lists serial ports)"
        )
    try:
        ROBOTS.params(kind, {}, where="params")
    except PluginError as exc:
        return f"{kind} needs params ({exc}): add it to edge.robots by hand"
    return ""


def simulated_kinds() -> list[str]:
    """Robot kinds `discover --sim` can add: simulators that run without params."""
    from edge_agent.robot import known_robot_kinds

    return [kind for kind in known_robot_kinds() if not _sim_refusal(kind)]


def _camera_size(camera: dict[str, Any]) -> str:
    """A lerobot robot's camera needs width, height and fps: the probed defaults, else common ones."""
    prof = camera.get("default_stream_profile") or {}
    size = {"width": 640, "height": 480, "fps": 30} | {k: prof[k] for k in ("width", "height", "fps") if prof.get(k)}
    return ", ".join(f"{k}: {v}" for k, v in size.items())


def _arm_hint(port: SerialPort, index: int, cams: list[dict[str, Any]]) -> str:
    """A commented lerobot robot entry for an arm on `port` (its lerobot type guessed from the bus adapter)."""
    lerobot_type = "koch_follower" if "Dynamixel" in (port.arm_bridge or "") else "so101_follower"
    cameras = ", ".join(
        f"cam{j}: {{type: opencv, index_or_path: {c.get('id')}, {_camera_size(c)}}}" for j, c in enumerate(cams)
    )
    config = f"port: {port.device}" + (f", cameras: {{{cameras}}}" if cams else "")
    return f"#   - {{id: arm-{index}, kind: lerobot, params: {{type: {lerobot_type}, config: {{{config}}}}}}}"


def discover(
    control_addr: str,
    sims: list[str],
    serial: Callable[[], list[SerialPort]] = find_serial_ports,
    cameras: Callable[[], list[dict[str, Any]]] = find_cameras,
) -> str:
    """A commented edge config (YAML) for this PC."""
    from edge_agent.robot import known_robot_kinds

    kinds, sim_kinds = known_robot_kinds(), simulated_kinds()
    unknown = [s for s in sims if s not in kinds]
    if unknown:
        raise ValueError(f"unknown simulated robot kind(s) {unknown}; known: {sim_kinds}")
    for kind in sims:
        if why := _sim_refusal(kind):
            raise ValueError(f"--sim {kind}: {why}; --sim takes {sim_kinds}")
    host = socket.gethostname().split(".")[0] or "edge"
    agent = "".join(c if c.isalnum() or c in "-_." else "-" for c in host)[:64]
    robots = [{"id": f"{kind.replace('_', '-')}-{i}", "kind": kind} for i, kind in enumerate(sims)]
    ports, cams = serial(), cameras()
    config = {
        "auth": {"enabled": True},  # the token: USER_TOKEN in ENV_FILE (the comment below says so)
        "edge": {
            "agent_id": agent,
            "control_addr": control_addr,
            "replay_addr": control_addr.rsplit(":", 1)[0] + ":50052",
            "inference_addr": control_addr.rsplit(":", 1)[0] + ":50053",
            "learner_addr": control_addr.rsplit(":", 1)[0] + ":50054",
            "metrics_host": "127.0.0.1",
            "robots": robots,
        },
    }
    lines = [f"# userctl edge discover on {host}: {len(ports)} serial port(s), {len(cams)} camera(s)"]
    for p in ports:
        what = p.arm_bridge or "not a known arm bus adapter"
        lines.append(f"#   serial {p.device}  usb {p.vid or '?'}:{p.pid or '?'} {p.description}  -> {what}")
    for c in cams:
        prof = c.get("default_stream_profile", {})
        lines.append(
            f"#   camera {c.get('id')}  {prof.get('width', '?')}x{prof.get('height', '?')} @ {prof.get('fps', '?')} fps"
        )
    arms = [p for p in ports if p.arm_bridge]
    if arms:
        needs = "" if "lerobot" in kinds else " (the lerobot kind needs the lerobot package)"
        lines.append(f"# Arms found; to drive one, add it to edge.robots (type: its lerobot robot type){needs}:")
        lines += [_arm_hint(p, i, cams) for i, p in enumerate(arms)]
    if not robots:
        lines.append("# No simulated robot asked for (--sim KIND); add robots before starting the agent.")
    lines += [
        f"# Token: USER_TOKEN=<this PC's edge token> in {ENV_FILE} (mode 0600), which the systemd unit reads.",
        "# edge.metrics_host: 127.0.0.1 keeps /metrics (no auth) on this PC; 0.0.0.0 lets the lab's Prometheus",
        "# scrape it (deploy/prometheus/edges.yml lists robot PCs): open it only to a trusted network.",
    ]
    return "\n".join(lines) + "\n" + yaml.safe_dump(config, sort_keys=False)


# --------------------------------------------------------------------------- systemd


def _exec_word(arg: str, executable: bool = False) -> str:
    """`arg` as one word of an ExecStart= line (systemd.service, "Command lines").

    systemd expands %specifiers on the whole line, splits it on whitespace, unquotes and C-unescapes each
    word, then expands $VARS in the arguments (not in the executable's path, where "$$" would stay "$$").
    """
    word = arg.replace("%", "%%") if executable else arg.replace("%", "%%").replace("$", "$$")
    if word and not any(c in word for c in " \t\"'\\"):
        return word  # plain paths stay as they were
    return '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'


def render_unit(userctl: str, config: str, user: str, env_file: str = ENV_FILE) -> str:
    for value in (userctl, config, user, env_file):
        if not value.isprintable():  # a newline would end the setting and start another
            raise ValueError(f"{value!r} has a control character, which a unit file cannot hold")
    exec_start = f"{_exec_word(userctl, executable=True)} edge --config {_exec_word(config)}"
    user, env_file = user.replace("%", "%%"), env_file.replace("%", "%%")  # specifiers; these are not unquoted
    return f"""[Unit]
Description=USER edge agent (the robots of this PC)
Wants=network-online.target
After=network-online.target
# Keep retrying forever: a robot PC should rejoin the fleet without a person.
StartLimitIntervalSec=0

[Service]
Type=simple
User={user}
SupplementaryGroups=dialout video
ExecStart={exec_start}
# Relative paths of the config (edge.spool_dir: the outbox of unsent steps) live here, owned by User.
StateDirectory=user-edge
WorkingDirectory=/var/lib/user-edge
EnvironmentFile=-{env_file}
Environment=MUJOCO_GL=egl PYTHONUNBUFFERED=1 MALLOC_ARENA_MAX=2
Restart=on-failure
RestartSec=2
# SIGTERM: the agent holds the robots still, flushes unacknowledged steps and deregisters.
KillSignal=SIGTERM
TimeoutStopSec=30
StandardOutput=journal
StandardError=journal
SyslogIdentifier=user-edge
NoNewPrivileges=yes
ProtectSystem=full
PrivateTmp=yes

[Install]
WantedBy=multi-user.target
"""


def _hidden_by_private_tmp(config: str) -> str:
    """Why the service could not read `config` (the unit has PrivateTmp=yes), or "" when it can."""
    if any(Path(config).is_relative_to(tmp) for tmp in ("/tmp", "/var/tmp")):
        why = "which the service (PrivateTmp=yes) cannot see: copy it to /etc/user"
        return f"{config} is under a temporary directory, {why}"
    return ""


def edge_config_problem(config: str) -> str:
    """Why `userctl edge --config config` would refuse to start (naming the field), or "" when it would not.

    The checks the agent makes before touching a robot: the file loads as a stack config, and every robot,
    task and teleoperator entry names a registered kind with valid params.
    """
    from user.config import ConfigError, load_config
    from user.registry import PluginError

    if not Path(config).is_file():
        return f"edge config {config} " + ("is not a file" if Path(config).exists() else "does not exist")
    try:
        cfg = load_config(config, environ={})  # the installer's USER__* variables are not the service's
    except ConfigError as exc:
        message = " ".join(str(exc).split())  # YAML errors span lines
        return message if config in message else f"{config}: {message}"
    from edge_agent.robot import ROBOTS
    from edge_agent.task import TASKS
    from edge_agent.teleop import TELEOPERATORS

    try:
        for i, rc in enumerate(cfg.edge.robots):
            ROBOTS.params(rc.kind, rc.params, where=f"edge.robots[{i}].params")
            if rc.task is not None:
                TASKS.params(rc.task.kind, rc.task.params, where=f"edge.robots[{i}].task.params")
            if rc.teleop is not None:
                TELEOPERATORS.params(rc.teleop.kind, rc.teleop.params, where=f"edge.robots[{i}].teleop.params")
    except PluginError as exc:
        return f"{config}: {exc}"
    return ""


def _edge_auth(config: str) -> AuthConfig | None:
    """The auth section the service would run with; None when the config does not load (reported elsewhere)."""
    from user.config import ConfigError, load_config

    try:
        return load_config(config, environ={}).auth
    except ConfigError:
        return None


def _env_file_token(env_file: str) -> str | None:
    """USER_TOKEN's value in the unit's EnvironmentFile ("" when absent); None when this user cannot read it
    (systemd reads it as root, so that is no problem)."""
    try:
        lines = Path(env_file).read_text().splitlines()
    except FileNotFoundError:
        return ""
    except (OSError, UnicodeDecodeError):
        return None
    values = [m.group(1) for line in lines if (m := ENV_TOKEN.match(line))]
    return values[-1] if values else ""


def token_problem(config: str, env_file: str) -> str:
    """Why the service would stop at start for want of a usable token (the config's auth.token_file is missing or
    unreadable, or a token is the example placeholder), or "". $USER_TOKEN from env_file wins over token_file."""
    from user.auth import is_placeholder
    from user.config import ConfigError, read_token_file

    auth = _edge_auth(config)
    if auth is None or not auth.enabled:
        return ""
    if auth.token:  # wins over $USER_TOKEN and auth.token_file
        return "auth.token is an example placeholder (REPLACE-ME)" if is_placeholder(auth.token) else ""
    env_token = _env_file_token(env_file)
    if env_token:  # wins over auth.token_file
        return f"{env_file}: USER_TOKEN is an example placeholder (REPLACE-ME)" if is_placeholder(env_token) else ""
    if env_token is None or auth.token_file is None:
        return ""  # unreadable here (systemd reads it as root), or the USER_TOKEN route not set up yet: token_note
    if hidden := _hidden_by_private_tmp(str(auth.token_file)):
        return f"auth.token_file: {hidden}"
    try:
        token = read_token_file(auth.token_file)
    except ConfigError as exc:
        return f"{exc}: put this PC's edge token there (readable by the service's user) or USER_TOKEN=... in {env_file}"
    if is_placeholder(token):
        return f"auth.token_file {auth.token_file}: the token is an example placeholder (REPLACE-ME)"
    return ""


def token_note(config: str, env_file: str) -> str:
    """How to give the service its token when the config names none and env_file has no USER_TOKEN yet, or ""."""
    auth = _edge_auth(config)
    if auth is None or not auth.enabled or auth.token or auth.token_file or _env_file_token(env_file) != "":
        return ""
    return (
        f"the config names no token: put USER_TOKEN=<this PC's edge token> in {env_file} (mode 0600, read by "
        "systemd), or the agent stops at each start with `auth.token: ... no token is set`"
    )


def _unit_name_problem(name: str) -> str:
    if UNIT_NAME.fullmatch(name) and not name.startswith("-") and len(f"{name}.service") <= UNIT_NAME_MAX:
        return ""
    return (
        f"invalid unit name {name!r} (--name): systemd allows letters, digits and : _ . - \\ "
        f"(not first -), at most {UNIT_NAME_MAX - len('.service')} characters"
    )


def _userctl_problem(userctl: str) -> str:
    if any(c in userctl for c in "\"'\\"):  # systemd refuses such an executable path
        return f"systemd cannot run {userctl} (--userctl): its path has a quote or backslash"
    if not (os.path.isfile(userctl) and os.access(userctl, os.X_OK)):
        return f"{userctl} is not an executable file (--userctl)"
    return ""


def _user_problem(user: str) -> str:
    if user.isdigit():  # systemd takes a numeric uid as is
        return ""
    try:
        pwd.getpwnam(user)
    except KeyError:
        return f"user {user!r} does not exist on this machine (--user); the service could not start"
    return ""


def _unit_dir_problem(unit_dir: str) -> str:
    if Path(unit_dir).is_dir():
        return ""
    return f"unit directory {unit_dir} " + ("is not a directory" if Path(unit_dir).exists() else "does not exist")


def install_service(args: argparse.Namespace) -> int:
    def fail(message: str, code: int = 2) -> int:
        print(f"userctl edge install-service: {message}", file=sys.stderr)
        return code

    name = args.name.removesuffix(".service")
    if problem := _unit_name_problem(name):
        return fail(problem)
    userctl = args.userctl or shutil.which("userctl") or str(Path(sys.executable).with_name("userctl"))
    # ExecStart needs an absolute path (a bare name is looked up on PATH); abspath keeps the venv's symlink.
    userctl = os.path.abspath(userctl if "/" in userctl else shutil.which(userctl) or userctl)
    config = os.path.realpath(args.config)
    options = (("--config", config), ("--userctl", userctl), ("--user", args.user), ("--env-file", args.env_file))
    for option, value in options:
        if not value.isprintable():
            return fail(f"{option} {value!r} has a control character, which a unit file cannot hold")
    unit = render_unit(userctl, config, args.user, args.env_file)
    path = Path(args.unit_dir) / f"{name}.service"
    # Each of these would leave a unit that fails at every start, restarted every 2 s for ever.
    problems = [
        _hidden_by_private_tmp(config),
        edge_config_problem(config),
        token_problem(config, args.env_file),
        _user_problem(args.user),
        _userctl_problem(userctl),
        _unit_dir_problem(args.unit_dir),
    ]
    problems = [p for p in problems if p]
    note = token_note(config, args.env_file)
    if args.dry_run:
        notes = "".join(f"# WARNING: {p}\n" for p in problems) + (f"# NOTE: {note}\n" if note else "")
        print(f"# would write {path}\n" + notes + unit, end="")
        return 0
    if problems:
        return fail(problems[0])
    if note:  # not refused: the token may well be written after the unit; said once, not in every restart's log
        print(f"userctl edge install-service: note: {note}", file=sys.stderr)
    try:
        path.write_text(unit)
    except PermissionError:
        return fail(f"cannot write {path}; run with sudo (or --dry-run)", 1)
    except OSError as exc:
        return fail(f"cannot write {path}: {exc.strerror or exc}", 1)
    print(f"wrote {path}")
    if args.no_start:
        return 0
    for cmd in (["systemctl", "daemon-reload"], ["systemctl", "enable", "--now", name]):
        if subprocess.run(cmd).returncode != 0:
            return fail(f"{' '.join(cmd)} failed", 1)
    print(f"started; logs: journalctl -u {name} -f")
    return 0


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="userctl edge", description=__doc__)
    sub = parser.add_subparsers(dest="action", required=True)
    d = sub.add_parser("discover", help="probe cameras, serial ports and sims; print an edge config")
    d.add_argument("--control", default="127.0.0.1:50051", help="control address the config points at")
    d.add_argument("--sim", action="append", default=[], metavar="KIND", help="add a simulated robot of KIND")
    d.add_argument("--output", "-o", help="write the config here instead of stdout")
    i = sub.add_parser("install-service", help="install and start the systemd unit of the edge agent")
    i.add_argument("--config", "-c", required=True, help="edge config the service runs")
    i.add_argument("--user", default=os.environ.get("SUDO_USER") or getpass.getuser(), help="account it runs as")
    i.add_argument("--name", default="user-edge", help="unit name")
    i.add_argument("--unit-dir", default="/etc/systemd/system")
    i.add_argument("--userctl", help="path of userctl (default: the one on PATH)")
    i.add_argument("--env-file", default=ENV_FILE, help="the unit's EnvironmentFile: USER_TOKEN=... (the token)")
    i.add_argument("--dry-run", action="store_true", help="print the unit instead of installing it")
    i.add_argument("--no-start", action="store_true", help="write the unit only")
    args = parser.parse_args(argv)
    if args.action == "install-service":
        return install_service(args)
    try:
        text = discover(args.control, args.sim)
    except ValueError as exc:
        print(f"userctl edge discover: {exc}", file=sys.stderr)
        return 2
    if args.output:
        try:
            Path(args.output).write_text(text)
        except OSError as exc:  # a missing folder, a directory, no permission
            print(f"userctl edge discover: cannot write {args.output}: {exc.strerror or exc}", file=sys.stderr)
            return 1 if isinstance(exc, PermissionError) else 2
        print(f"wrote {args.output}")
    else:
        print(text, end="")
    return 0
