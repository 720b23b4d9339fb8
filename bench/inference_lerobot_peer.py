"""One robot, a tiny SmolVLA from a local folder: our InferenceService vs lerobot's own async-inference
PolicyServer (lerobot.async_inference.policy_server, 0.6.1), both on 127.0.0.1 and offline.

lerobot's server is started as its own process with its own CLI (HF_HUB_OFFLINE=1, one torch thread,
inference_latency=0 so it does not pad answers to 1/fps). The robot speaks lerobot's robot-client
protocol: Ready, SendPolicyInstructions (a pickled RemotePolicyConfig naming policy type "smolvla" and
the checkpoint folder), then per chunk SendObservations (a pickled TimedObservation streamed in chunks,
must_go so none is filtered) followed by GetActions (a pickled list of TimedAction). The robot does not
unpickle the answer (no pickle.loads here: it checks that bytes came back), so lerobot's timing leaves
out one small unpickle a real client does. lerobot's RobotClient itself needs a lerobot Robot (hardware
driver), hence this loop of the same calls.

Only one robot: the server keeps one observation queue of size 1 for all clients, each client's Ready
resets it, and GetActions answers the newest observation whoever sent it, so a second robot would get
the first one's chunks. Ours serves the same folder (the smolvla policy kind, lerobot's own loading
path) with an Act per chunk.
"""

from __future__ import annotations

import os
import pickle  # only to build requests for lerobot's server, which takes pickles on its wire
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from bench import Row, median
from edge_agent.encoder import encode_observation
from user import rpc
from user.config import AuthConfig, StackConfig
from user.v1 import inference_pb2, inference_pb2_grpc
from user.v1 import tensor_pb2 as tpb

PEER = "lerobot async_inference PolicyServer (0.6.1)"
WORDS = ["reach", "the", "red", "green", "blue", "target"]
INSTRUCTION = "reach the red target"
IMAGE, STATE, ACTION, HORIZON = 64, 6, 6, 8
MOTORS = [f"j{i}.pos" for i in range(STATE)]
START_TIMEOUT_S = 300.0  # importing lerobot + torch in a fresh process takes a while on a busy machine
RPC_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Setup:
    """What the robot sends: its cameras and their size, the frames (keyed camera.<name>; () = noise frames),
    and for ours whether the edge JPEG-encodes them (lerobot's client always pickles them raw)."""

    image: int = IMAGE
    cameras: tuple[str, ...] = ("front",)
    frames: tuple[dict[str, np.ndarray], ...] = ()
    jpeg_quality: int = 0


def build_checkpoint(root: Path, setup: Setup = Setup()) -> Path:
    import torch
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from user.policies.smolvla import make_tiny_backbone, save_checkpoint, tiny_smolvla_config

    backbone = make_tiny_backbone(root / "backbone", WORDS, image_size=setup.image)
    torch.manual_seed(0)
    cameras = list(setup.cameras)
    config = tiny_smolvla_config(backbone, cameras, STATE, ACTION, horizon=HORIZON, image_size=setup.image)
    return save_checkpoint(SmolVLAPolicy(config), root / "checkpoint")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_lerobot(root: Path) -> tuple[str, subprocess.Popen]:
    port = _free_port()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    args = ["--host=127.0.0.1", f"--port={port}", "--fps=30", "--inference_latency=0", "--obs_queue_timeout=5"]
    log = open(root / "policy_server.log", "w")  # noqa: SIM115 - the process owns it until it ends
    proc = subprocess.Popen(
        [sys.executable, "-m", "lerobot.async_inference.policy_server", *args],
        cwd=root,  # it writes logs/ into its working directory
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    addr = f"127.0.0.1:{port}"
    # Its import of lerobot + transformers takes a core for tens of seconds: done before any window opens.
    with grpc.insecure_channel(addr) as channel:
        grpc.channel_ready_future(channel).result(timeout=START_TIMEOUT_S)
    return addr, proc


@dataclass(frozen=True)
class Task:
    side: str  # "ours" | "lerobot"
    addr: str
    checkpoint: str
    seconds: float  # the window opens once the robot is connected and warmed up (one robot: no sync)
    token: str
    setup: Setup = Setup()


def _observations(setup: Setup, n: int = 8) -> list[tuple[dict[str, np.ndarray], np.ndarray]]:
    """(camera name -> frame, state) n times."""
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        if setup.frames:
            images = {c: setup.frames[i % len(setup.frames)][f"camera.{c}"] for c in setup.cameras}
        else:
            images = {c: rng.integers(0, 256, (setup.image, setup.image, 3), dtype=np.uint8) for c in setup.cameras}
        out.append((images, rng.standard_normal(STATE).astype(np.float32)))
    return out


def _ours_calls(task: Task) -> Callable[[int], None]:
    channel = rpc.make_channel(task.addr, AuthConfig(token=task.token))
    stub = inference_pb2_grpc.InferenceStub(channel)
    setup = task.setup
    plan = (
        {f"camera.{c}": (tpb.ENCODING_JPEG, setup.jpeg_quality) for c in setup.cameras} if setup.jpeg_quality else None
    )
    requests = [
        inference_pb2.ActRequest(
            robot_id="arm-0",
            observation=encode_observation({**{f"camera.{c}": v for c, v in images.items()}, "state": state}, plan),
            instruction=INSTRUCTION,
        )
        for images, state in _observations(setup)
    ]

    def call(i: int) -> None:
        resp = stub.Act(requests[i % len(requests)], timeout=RPC_TIMEOUT_S, wait_for_ready=True)
        if resp.horizon != HORIZON:
            raise RuntimeError(f"ours answered a chunk of {resp.horizon}")

    return call


def _lerobot_calls(task: Task) -> Callable[[int], None]:
    from lerobot.async_inference.helpers import RemotePolicyConfig, TimedObservation
    from lerobot.transport import services_pb2, services_pb2_grpc
    from lerobot.transport.utils import send_bytes_in_chunks
    from lerobot.utils.feature_utils import hw_to_dataset_features

    channel = grpc.insecure_channel(task.addr)
    grpc.channel_ready_future(channel).result(timeout=START_TIMEOUT_S)
    stub = services_pb2_grpc.AsyncInferenceStub(channel)
    setup = task.setup
    cameras = {c: (setup.image, setup.image, 3) for c in setup.cameras}
    features = hw_to_dataset_features({**dict.fromkeys(MOTORS, float), **cameras}, "observation")
    stub.Ready(services_pb2.Empty(), timeout=RPC_TIMEOUT_S)
    policy = RemotePolicyConfig("smolvla", task.checkpoint, features, HORIZON, "cpu")
    stub.SendPolicyInstructions(services_pb2.PolicySetup(data=pickle.dumps(policy)), timeout=RPC_TIMEOUT_S)
    raws = [
        {**dict(zip(MOTORS, state.tolist(), strict=True)), **images, "task": INSTRUCTION}
        for images, state in _observations(setup)
    ]

    def call(i: int) -> None:
        obs = TimedObservation(
            timestamp=time.time(), timestep=i * HORIZON, observation=raws[i % len(raws)], must_go=True
        )
        stub.SendObservations(send_bytes_in_chunks(pickle.dumps(obs), services_pb2.Observation), timeout=RPC_TIMEOUT_S)
        if not stub.GetActions(services_pb2.Empty(), timeout=RPC_TIMEOUT_S).data:
            raise RuntimeError("lerobot's server answered no actions")

    return call


def _robot(task: Task) -> tuple[list[float], str]:
    """One robot process: (latencies ms per chunk inside the window, error or "")."""
    try:
        call = _ours_calls(task) if task.side == "ours" else _lerobot_calls(task)
        call(0)  # connect, load and warm up before the window
        call(1)
        latencies, i = [], 2
        end_at = time.time() + task.seconds
        while time.time() < end_at:
            start = time.perf_counter()
            call(i)
            latencies.append((time.perf_counter() - start) * 1e3)
            i += 1
        return latencies, ""
    except Exception as exc:  # reported: the error does not cross processes as is
        return [], f"{type(exc).__name__}: {exc}"


def start_ours(cfg: StackConfig, checkpoint: Path, setup: Setup = Setup()) -> tuple[str, Callable[[], None]]:
    from bench.inference_bench import start_ours as start
    from user.policies.smolvla import SmolVlaPolicy, SmolVlaSpec, policy_spec
    from user.weights import WeightSet

    spec = SmolVlaSpec(
        checkpoint=str(checkpoint),
        image_keys={f"camera.{c}": c for c in setup.cameras},
        state_keys=["state"],
        action_dim=ACTION,
        action_low=[-1e6] * ACTION,  # no clipping: lerobot's server does not clip either
        action_high=[1e6] * ACTION,
    )
    policy = SmolVlaPolicy.from_checkpoint(checkpoint, spec)
    return start(cfg, WeightSet(1, policy_spec(spec), policy.tensors()))


def measure(
    pool: Any,
    root: Path,
    checkpoint: Path,
    sides: dict[str, tuple[str, str, Setup]],
    token: str,
    rounds: int,
    seconds: float,
) -> dict[str, list[float]]:
    """Chunk latencies (ms) per side label; sides: label -> ("ours" | "lerobot", address, what the robot sends).
    The sides take turns, one robot at a time."""
    lat: dict[str, list[float]] = {label: [] for label in sides}
    for _ in range(rounds):
        for label, (kind, addr, setup) in sides.items():
            latencies, error = pool.apply_async(
                _robot, (Task(kind, addr, str(checkpoint), seconds, token, setup),)
            ).get()
            if error:
                raise RuntimeError(f"{label}: {error} (lerobot log: {root / 'policy_server.log'})")
            lat[label] += latencies
    return lat


def stop_lerobot(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


def run(pool: Any, cfg: StackConfig, token: str, workdir: Path, quick: bool, log: Callable[..., None]) -> list[Row]:
    rounds, seconds = (1, 1.0) if quick else (2, 4.0)
    root = workdir / "lerobot_peer"
    root.mkdir(parents=True, exist_ok=True)
    checkpoint = build_checkpoint(root)
    log("inference_vla: tiny SmolVLA, 1 robot, ours vs lerobot's async-inference PolicyServer")
    lerobot_addr, proc = start_lerobot(root)
    ours_addr, stop_ours = start_ours(cfg, checkpoint)
    try:
        sides = {"ours": ("ours", ours_addr, Setup()), "lerobot": ("lerobot", lerobot_addr, Setup())}
        lat = measure(pool, root, checkpoint, sides, token, rounds, seconds)
    finally:
        stop_ours()
        stop_lerobot(proc)
    group = "inference SmolVLA (tiny, local folder, chunk 8x6), closed loop, 1 robot, lerobot's own protocol"
    return rows(
        group, lat, rounds * seconds, "ours: one Act per chunk; lerobot: SendObservations + GetActions per chunk"
    )


def rows(group: str, lat: dict[str, list[float]], seconds: float, note: str, ours: str = "ours") -> list[Row]:
    """chunks/s, p50 and p99: lat[ours] vs lat["lerobot"]."""
    rate = {s: len(v) / seconds for s, v in lat.items()}
    return [
        Row(group, "chunks/s", rate[ours], rate["lerobot"], "calls/s", True, note, PEER),
        Row(group, "chunk latency p50", median(lat[ours]), median(lat["lerobot"]), "ms", False, "", PEER),
        Row(
            group,
            "chunk latency p99",
            float(np.percentile(lat[ours], 99)),
            float(np.percentile(lat["lerobot"], 99)),
            "ms",
            False,
            "",
            PEER,
        ),
    ]
