"""Setting up a robot PC: `userctl edge discover` and `userctl edge install-service`.

discover probes what is attached — OpenCV cameras (through lerobot's finder), serial ports of
Feetech/Dynamixel bus adapters (the lerobot arms: SO-100/101, Koch), and the simulated robots this build
knows — and prints an edge config that validates (`userctl edge -c` runs it). Hardware without a USER
robot kind yet is listed as commented entries with its port, so nothing is guessed into a broken config.

install-service writes the systemd unit (restart on failure, logs to journald) and enables it.
"""

from __future__ import annotations

import argparse
import getpass
import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

# USB bridges the lerobot arms use: Feetech boards (CH340/CH343, STM32 CDC) and Dynamixel's U2D2 (FTDI).
ARM_BRIDGES = {
    ("1a86", "7523"): "CH340 (Feetech bus: SO-100/SO-101)",
    ("1a86", "55d3"): "CH343 (Feetech bus: SO-100/SO-101)",
    ("0483", "5740"): "STM32 CDC (Feetech bus)",
    ("0403", "6014"): "FTDI FT232H (Dynamixel U2D2: Koch)",
    ("0403", "6001"): "FTDI FT232R (Dynamixel)",
}
SERIAL_GLOBS = ("ttyACM*", "ttyUSB*")


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


def discover(
    control_addr: str,
    sims: list[str],
    serial: Callable[[], list[SerialPort]] = find_serial_ports,
    cameras: Callable[[], list[dict[str, Any]]] = find_cameras,
) -> str:
    """A commented edge config (YAML) for this PC."""
    from edge_agent.robot import known_robot_kinds

    kinds = known_robot_kinds()
    unknown = [s for s in sims if s not in kinds]
    if unknown:
        raise ValueError(f"unknown simulated robot kind(s) {unknown}; known: {kinds}")
    host = socket.gethostname().split(".")[0] or "edge"
    agent = "".join(c if c.isalnum() or c in "-_." else "-" for c in host)[:64]
    robots = [{"id": f"{kind.replace('_', '-')}-{i}", "kind": kind} for i, kind in enumerate(sims)]
    ports, cams = serial(), cameras()
    config = {
        "auth": {"enabled": True, "token_file": "/etc/user/edge.token"},
        "edge": {
            "agent_id": agent,
            "control_addr": control_addr,
            "replay_addr": control_addr.rsplit(":", 1)[0] + ":50052",
            "inference_addr": control_addr.rsplit(":", 1)[0] + ":50053",
            "learner_addr": control_addr.rsplit(":", 1)[0] + ":50054",
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
        lines.append("# Arms found; add a robot entry once a USER robot kind wraps its lerobot driver, e.g.:")
        for i, p in enumerate(arms):
            cams_yaml = ", ".join(f"{{id: {c.get('id')}}}" for c in cams)
            lines.append(
                f"#   - {{id: arm-{i}, kind: so101_follower, params: {{port: {p.device}, cameras: [{cams_yaml}]}}}}"
            )
    if not robots:
        lines.append("# No simulated robot asked for (--sim KIND); add robots before starting the agent.")
    return "\n".join(lines) + "\n" + yaml.safe_dump(config, sort_keys=False)


# --------------------------------------------------------------------------- systemd


def render_unit(userctl: str, config: str, user: str, env_file: str = "/etc/user/edge.env") -> str:
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
ExecStart={userctl} edge --config {config}
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


def install_service(args: argparse.Namespace) -> int:
    userctl = args.userctl or shutil.which("userctl") or str(Path(sys.executable).with_name("userctl"))
    config = str(Path(args.config).resolve())
    unit = render_unit(userctl, config, args.user)
    path = Path(args.unit_dir) / f"{args.name}.service"
    hidden = _hidden_by_private_tmp(config)
    if args.dry_run:
        print(f"# would write {path}\n" + (f"# WARNING: {hidden}\n" if hidden else "") + unit, end="")
        return 0
    if hidden:
        print(f"userctl edge install-service: {hidden}", file=sys.stderr)
        return 2
    try:
        path.write_text(unit)
    except PermissionError:
        print(f"userctl edge install-service: cannot write {path}; run with sudo (or --dry-run)", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    if args.no_start:
        return 0
    for cmd in (["systemctl", "daemon-reload"], ["systemctl", "enable", "--now", args.name]):
        if subprocess.run(cmd).returncode != 0:
            print(f"userctl edge install-service: {' '.join(cmd)} failed", file=sys.stderr)
            return 1
    print(f"started; logs: journalctl -u {args.name} -f")
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
        Path(args.output).write_text(text)
        print(f"wrote {args.output}")
    else:
        print(text, end="")
    return 0
