"""VLA inference for robots on a slow link: camera frames JPEG-encoded on the edge vs sent raw, at 20 Mbit/s.

A robot on a lab's Wi-Fi or at a remote site sends every Act its camera frames. Two raw 128x128 RGB
frames are 98 kB, so at 20 Mbit/s the request alone takes ~40 ms on the wire, and a handful of robots
fill the link. With `edge.robots[i].act_image_encoding` (or `image_encoding`, which it follows by default)
the edge sends them as JPEG (q90: ~6 kB for gym-hil Panda frames) and inference decodes them.

The link is emulated as in bench/weights_link.py: a private network namespace whose loopback has a
1500-byte MTU and a tc tbf qdisc at 20 Mbit/s; the parent starts `python -m bench.inference_link --child`
inside it and reads its rows (or one row saying why it was skipped). In the child, both servers (ours,
and the one-request-at-a-time server of the same model, as openpi's and lerobot's servers serve) and
the robots (separate processes, bench/inference_vla_bench.py's) all talk over that link. The frames are
real renders of gym-hil's Panda pick-cube scene (front and wrist cameras); the model is the VLA-sized
flow_vla of bench/inference_vla_bench.py. Robots ask for a chunk every 8 ticks at 30 Hz (3.75 Hz each).
"""

from __future__ import annotations

import multiprocessing
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bench import Row, median
from bench.netns import child_main, emit_rows

RATE = "20mbit"  # bench.netns.SLOW_LINK
JPEG_QUALITY = 90
EVERY = 8  # control ticks per chunk request (chunks of 16 at 30 Hz, asked for half-way)
OURS_RAW = "ours, raw frames (same server, the edge not encoding)"


def run(quick: bool, log: Callable[..., None] = print) -> list[Row]:
    from bench.netns import SLOW_LINK, link_rows

    args = ["bench.inference_link", "--child"] + (["--quick"] if quick else [])
    return link_rows(SLOW_LINK, args, "VLA inference over 20 Mbit/s (tc tbf in a netns)", log)


def panda_frames(count: int, size: int) -> tuple[dict[str, np.ndarray], ...]:
    """Front and wrist frames of gym-hil's Panda scene at `count` moments of a random-action episode."""
    from edge_agent.robot import action_bounds, make_robot

    robot = make_robot("gym_hil_panda", "panda-0", {"cameras": True, "camera_size": size}, seed=0)
    rng = np.random.default_rng(0)
    frames = []
    try:
        robot.reset(seed=0)
        low, high = action_bounds(robot.spec)
        for _ in range(count):
            for _ in range(5):
                robot.act(rng.uniform(low, high).astype(np.float32))
            obs = robot.observe()
            frames.append({k: v.copy() for k, v in obs.features.items() if k.startswith("camera.")})
    finally:
        robot.close()
    return tuple(frames)


def _rows(
    group: str, lat: dict[str, list[float]], rate: dict[str, float], offered: float, period_ms: float, note: str
) -> list[Row]:
    """Ours with JPEG frames against ours with raw frames and against the one-at-a-time server (raw)."""
    from bench.inference_vla_bench import PEER, _p99

    rows = []
    for side, name in (("ours raw", OURS_RAW), ("peer raw", PEER + ", raw frames")):
        ours = "ours JPEG"
        rows += [
            Row(group, f"Act round trip p50 vs {side}", median(lat[ours]), median(lat[side]), "ms", False, note, name),
            Row(group, f"Act round trip p99 vs {side}", _p99(lat[ours]), _p99(lat[side]), "ms", False, "", name),
            Row(
                group,
                f"chunks served/s (offered {offered:.1f}) vs {side}",
                rate[ours],
                rate[side],
                "calls/s",
                True,
                f"a chunk is due every {period_ms:.0f} ms",
                name,
            ),
        ]
    return rows


def _child(quick: bool) -> None:
    import torch

    from bench.inference_bench import start_ours
    from bench.inference_vla_bench import (
        CONTROL_HZ,
        OBSERVATIONS_PER_ROBOT,
        TOKEN,
        VLA,
        _warm,
        drive,
        make_weights,
        start_peer,
    )
    from user import wire
    from user.config import AuthConfig, ServerConfig, load_config
    from user.v1 import tensor_pb2 as tpb

    profile = replace(VLA, hidden=256) if quick else VLA
    frames = panda_frames(OBSERVATIONS_PER_ROBOT, profile.image)
    raw_bytes = float(sum(f.nbytes for f in frames[0].values()))
    raw_kb = raw_bytes / 1e3
    jpeg_bytes = float(
        np.mean([sum(len(wire.encode_image(f, tpb.ENCODING_JPEG, JPEG_QUALITY)) for f in fr.values()) for fr in frames])
    )
    cfg = load_config(None, [])
    cfg.auth = AuthConfig(token=TOKEN)
    cfg.inference.server = ServerConfig(host="127.0.0.1", port=0, metrics_port=0, grace_s=0.5, max_workers=64)
    cfg.inference.max_batch = 32
    cfg.inference.max_wait_ms = 5.0
    torch.set_num_threads(1)
    weights = make_weights(profile)
    n_params = sum(int(v.size) for v in weights.tensors.values())
    counts = (1,) if quick else (1, 8)
    seconds, rounds = (1.5, 1) if quick else (10.0, 2)
    hz = CONTROL_HZ / EVERY
    sides = {"ours JPEG": ("ours", JPEG_QUALITY), "ours raw": ("ours", 0), "peer raw": ("peer", 0)}
    rows: list[Row] = []
    servers = {"ours": start_ours(cfg, weights), "peer": start_peer(cfg, weights)}
    try:
        with multiprocessing.get_context("spawn").Pool(max(counts)) as pool:
            pool.map(_warm, range(max(counts)), chunksize=1)
            for clients in counts:
                lat: dict[str, list[float]] = {side: [] for side in sides}
                calls = dict.fromkeys(sides, 0)
                for _ in range(rounds):  # the sides take turns, so background load hits each alike
                    for side, (server, quality) in sides.items():
                        print(f"LOG inference over {RATE}: {clients} robot(s), {side}", flush=True)
                        window = drive(pool, servers[server][0], profile, clients, seconds, 1.0 / hz, frames, quality)
                        lat[side] += window.latencies
                        calls[side] += window.calls
                rate = {side: n / (rounds * seconds) for side, n in calls.items()}
                group = (
                    f"VLA inference over {RATE[:-4]} Mbit/s (tc tbf in a netns): flow_vla {n_params / 1e6:.1f}M, "
                    f"two 128x128 gym-hil Panda camera frames, {clients} robot(s) x {hz:.2f} Hz"
                )
                note = f"ours: JPEG q{JPEG_QUALITY}, {jpeg_bytes / 1e3:.1f} kB of frames a request ({raw_kb:.1f} raw)"
                rows += _rows(group, lat, rate, clients * hz, 1e3 / hz, note)
                rows.append(Row(group, "camera bytes per request", jpeg_bytes, raw_bytes, "B", False, "", OURS_RAW))
            if not quick:  # lerobot's server imports lerobot + transformers: too slow for the smoke run
                rows += _lerobot_rows(pool, cfg, frames, jpeg_bytes, raw_kb)
    finally:
        for _addr, stop in servers.values():
            stop()
    emit_rows(rows)


def _lerobot_rows(
    pool: Any, cfg: Any, frames: tuple[dict[str, np.ndarray], ...], jpeg_bytes: float, raw_kb: float
) -> list[Row]:
    """One robot, tiny SmolVLA from a local folder, closed loop: ours (the edge's JPEG frames, and raw) vs
    lerobot's async-inference PolicyServer (its client pickles the raw frames) over the same link."""
    from bench import inference_lerobot_peer as peer
    from bench.inference_vla_bench import TOKEN

    setup = peer.Setup(image=128, cameras=("front", "wrist"), frames=frames)
    rounds, seconds = 1, 10.0  # one window per side (the flow_vla rows above alternate theirs)
    group = (
        f"inference SmolVLA (tiny, local folder, chunk 8x6) over {RATE[:-4]} Mbit/s (tc tbf in a netns), "
        "two 128x128 gym-hil Panda frames, closed loop, 1 robot, lerobot's own protocol"
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        checkpoint = peer.build_checkpoint(root, setup)
        lerobot_addr, proc = peer.start_lerobot(root)
        ours_addr, stop_ours = peer.start_ours(cfg, checkpoint, setup)
        try:
            print(f"LOG inference over {RATE}: tiny SmolVLA, 1 robot, ours vs lerobot's PolicyServer", flush=True)
            sides = {
                "ours JPEG": ("ours", ours_addr, replace(setup, jpeg_quality=JPEG_QUALITY)),
                "ours raw": ("ours", ours_addr, setup),
                "lerobot": ("lerobot", lerobot_addr, setup),
            }
            lat = peer.measure(pool, root, checkpoint, sides, TOKEN, rounds, seconds)
        except Exception as exc:  # the flow_vla rows above still count
            return [Row(group, "lerobot async_inference PolicyServer", "not run", f"{type(exc).__name__}: {exc}")]
        finally:
            stop_ours()
            peer.stop_lerobot(proc)
    note = (
        f"ours: JPEG q{JPEG_QUALITY}, {jpeg_bytes / 1e3:.1f} kB of frames a chunk request; lerobot: {raw_kb:.1f} kB raw"
    )
    out = peer.rows(group, lat, rounds * seconds, note, ours="ours JPEG")
    raw_note = "ours with the same raw frames lerobot sends: the protocol alone, without the edge's encoding"
    out.append(
        Row(
            group,
            "chunk latency p50, ours raw frames",
            median(lat["ours raw"]),
            median(lat["lerobot"]),
            "ms",
            False,
            raw_note,
            peer.PEER,
        )
    )
    return out


if __name__ == "__main__":
    child_main(_child, run)
