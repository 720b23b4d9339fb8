"""Replay buffer: durable LMDB ReplayStore (ours) vs lerobot's in-RAM ReplayBuffer (peer).

Both get the same transitions, built before timing starts: ours as user.v1.Step messages (what the
Replay service receives), theirs as the torch tensors their learner adds one by one (images as float32
in [0, 1], channel-first, as their pipeline feeds them). The peer is built like lerobot's learner
builds its online buffer (optimize_memory=True, storage on the CPU); DrQ augmentation is off so both
sample plain batches.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench import Row, median, repeat_ms, timed
from user.v1 import step_pb2
from user.wire import to_tensor, to_tensor_map

BATCH = 256
IN_FLIGHT = 8  # Insert requests a client has sent before it waits for their acks (a stream does not wait per step)
TURN = 8192  # steps each side inserts per turn: ours drains its window at the end of a turn, then the peer goes
EPISODE_LEN = 50
STATE_DIM = 15
ACTION_DIM = 3
IMAGE_HW = 128
CAMERAS = ("front", "wrist")
EDGE_JPEG_QUALITY = 90  # edge.robots[i].jpeg_quality's default


@dataclass(frozen=True)
class Shape:
    name: str
    images: bool
    smooth: bool = False  # camera-like frames (smooth scene + sensor noise) instead of uniform noise

    def observation(self, rng: np.random.Generator) -> dict[str, np.ndarray]:
        obs = {"state": rng.standard_normal(STATE_DIM).astype(np.float32)}
        if self.images:
            for cam in CAMERAS:
                obs[f"camera.{cam}"] = camera_frame(rng) if self.smooth else noise_frame(rng)
        return obs


def noise_frame(rng: np.random.Generator) -> np.ndarray:
    """Uniform noise: the worst case for any image codec."""
    return rng.integers(0, 256, (IMAGE_HW, IMAGE_HW, 3), dtype=np.uint8)


def camera_frame(rng: np.random.Generator) -> np.ndarray:
    """A smooth scene (shaded gradients at a random phase, per channel) plus +-3 sensor noise: what a camera sees
    compresses, noise does not."""
    yy, xx = np.mgrid[0:IMAGE_HW, 0:IMAGE_HW].astype(np.float32)
    phase = rng.uniform(0, 2 * np.pi, 3)
    chans = [110 + 90 * np.sin(xx / (9 + 4 * c) + phase[c]) * np.cos(yy / (13 + 3 * c) - phase[c]) for c in range(3)]
    img = np.stack(chans, axis=-1) + rng.integers(-3, 4, (IMAGE_HW, IMAGE_HW, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


SIM_ARM = Shape("sim-arm (state 15 f32, action 3)", images=False)
IMAGES = Shape(f"images (2 cams {IMAGE_HW}x{IMAGE_HW}x3 u8 noise, state 15)", images=True)
CAMERA = Shape(f"camera-like (2 cams {IMAGE_HW}x{IMAGE_HW}x3 u8, state 15)", images=True, smooth=True)


@dataclass
class Episode:
    """Observations o_0..o_T and actions a_0..a_{T-1}: T transitions."""

    observations: list[dict[str, np.ndarray]]
    actions: list[np.ndarray]
    rewards: list[float]


def make_episodes(shape: Shape, n: int, seed: int = 0) -> list[Episode]:
    rng = np.random.default_rng(seed)
    episodes, left = [], n
    while left > 0:
        length = min(EPISODE_LEN, left)
        episodes.append(
            Episode(
                [shape.observation(rng) for _ in range(length + 1)],
                [rng.uniform(-1, 1, ACTION_DIM).astype(np.float32) for _ in range(length)],
                [float(r) for r in rng.standard_normal(length)],
            )
        )
        left -= length
    return episodes


def to_steps(episodes: list[Episode], robot_id: str = "arm-0") -> list[step_pb2.Step]:
    """Steps as an edge agent sends them: the last step of an episode carries final_observation."""
    steps = []
    for e, ep in enumerate(episodes):
        length = len(ep.actions)
        for t in range(length):
            last = t == length - 1
            step = step_pb2.Step(
                robot_id=robot_id,
                episode_id=f"ep-{e}",
                step_index=t,
                observation=to_tensor_map(ep.observations[t]),
                action=to_tensor(ep.actions[t]),
                reward=ep.rewards[t],
                truncated=last,
                policy_version=1,
                observed_at_ns=1,
                acted_at_ns=2,
            )
            if last:
                step.final_observation.CopyFrom(to_tensor_map(ep.observations[t + 1]))
            steps.append(step)
    return steps


# --------------------------------------------------------------------------- ours


def open_store(path: Path, map_size_mb: int, **kw: Any) -> Any:
    from services.replay.store import ReplayStore

    return ReplayStore(path, map_size_mb=map_size_mb, **kw)


def store_transitions(store: Any) -> int:
    """Sampleable transitions the store holds."""
    return int(store.stats()["transitions"])


def insert_ours(store: Any, steps: list[step_pb2.Step], on_commit: Callable[[int], None] | None = None) -> None:
    """Requests of BATCH steps as an Insert stream sends them: up to IN_FLIGHT unacknowledged, the next sent as
    the oldest is acknowledged (an edge stream never stops to wait for all); returns when the last is acked."""
    futures: deque[Any] = deque()
    done = 0

    def ack() -> None:
        nonlocal done
        _stored, dups = futures.popleft().result()  # resolves after the commit (fsync) that holds these steps
        if dups:
            raise RuntimeError(f"{dups} unexpected duplicates")
        done = min(done + BATCH, len(steps))
        if on_commit is not None:
            on_commit(done)

    for i in range(0, len(steps), BATCH):
        if len(futures) >= IN_FLIGHT:
            ack()
        futures.append(store.submit(steps[i : i + BATCH]))
    while futures:
        ack()


def edge_encode(steps: list[step_pb2.Step], quality: int = EDGE_JPEG_QUALITY) -> tuple[list[step_pb2.Step], float, int]:
    """The steps as an edge with image_encoding {"*": "jpeg"} sends them: every camera frame JPEG-encoded the way
    edge_agent/encoder.py does it (wire.encode_image of the raw bytes in place). Returns (steps, seconds of
    encoding summed over frames, frames)."""
    from edge_agent.encoder import _encode
    from user.v1 import tensor_pb2 as tpb

    out, seconds, frames = [], 0.0, 0
    for step in steps:
        enc = step_pb2.Step()
        enc.CopyFrom(step)
        parts = [enc.observation] + ([enc.final_observation] if enc.HasField("final_observation") else [])
        for part in parts:
            for name, tensor in part.tensors.items():
                if name.startswith("camera."):
                    data, took = _encode(tensor, tpb.ENCODING_JPEG, quality)
                    tensor.data, tensor.encoding = data, tpb.ENCODING_JPEG
                    seconds += took
                    frames += 1
        out.append(enc)
    return out, seconds, frames


def replay_check_seconds(steps: list[step_pb2.Step]) -> tuple[float, int]:
    """What replay's Insert spends checking the encoded frames (user.wire.check_image, part of validate_step):
    (seconds, frames)."""
    from user import wire

    tensors = [
        t
        for st in steps
        for part in (st.observation, st.final_observation)
        for name, t in part.tensors.items()
        if name.startswith("camera.")
    ]
    seconds = timed(lambda: [wire.check_image(t) for t in tensors])[0]
    return seconds, len(tensors)


def map_size_for(shape: Shape, n: int) -> int:
    per = (2 * IMAGE_HW * IMAGE_HW * 3 + 1024) if shape.images else 1024
    return max(64, int(3 * n * per / 2**20) + 64)


def ours_resident_bytes(store: Any) -> int:
    """RAM the buffer holds for sampling: hot-tier columns plus the index (about 200 B per transition)."""
    return int(store.cache_info()["bytes"]) + 200 * store.transitions_for(["arm-0"])


# --------------------------------------------------------------------------- peer


def make_peer(capacity: int) -> Any:
    from lerobot.rl.buffer import ReplayBuffer

    # As lerobot's learner builds its online buffer (learner.py): CPU storage, optimize_memory=True.
    return ReplayBuffer(capacity=capacity, device="cpu", storage_device="cpu", optimize_memory=True, use_drq=False)


def peer_transitions(episodes: list[Episode]) -> list[dict[str, Any]]:
    """add() kwargs per transition, as lerobot's learner receives them from its actor."""
    import torch

    def state(obs: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        out = {"observation.state": torch.from_numpy(obs["state"]).unsqueeze(0)}
        for key, val in obs.items():
            if key.startswith("camera."):
                img = torch.from_numpy(val).permute(2, 0, 1).float().div_(255.0)
                out[f"observation.images.{key.removeprefix('camera.')}"] = img.unsqueeze(0)
        return out

    out = []
    for ep in episodes:
        states = [state(o) for o in ep.observations]  # next_state shares the tensors of the next state
        for t, action in enumerate(ep.actions):
            last = t == len(ep.actions) - 1
            out.append(
                {
                    "state": states[t],
                    "action": torch.from_numpy(action).unsqueeze(0),
                    "reward": ep.rewards[t],
                    "next_state": states[t + 1],
                    "done": False,
                    "truncated": last,
                }
            )
    return out


def peer_nbytes(buf: Any) -> int:
    tensors = [*buf.states.values(), buf.actions, buf.rewards, buf.dones, buf.truncateds, buf.episode_ends]
    if not buf.optimize_memory:
        tensors += list(buf.next_states.values())
    return sum(t.numel() * t.element_size() for t in tensors)


# --------------------------------------------------------------------------- crash survival


def crash_child(path: str, n: int, images: bool) -> None:
    """Insert n transitions, printing the steps acknowledged (committed) after each commit, forever."""
    shape = IMAGES if images else SIM_ARM
    store = open_store(Path(path), map_size_for(shape, n))
    steps = to_steps(make_episodes(shape, n, seed=1))

    def acked(k: int) -> None:
        print(k, flush=True)

    insert_ours(store, steps, acked)
    print("done", flush=True)
    signal.pause()


def crash_survival(workdir: Path, shape: Shape, n: int) -> tuple[int, int, int, int, int]:
    """SIGKILL the writer mid-ingest: (acked before the kill, steps kept, acked lost, duplicates after re-send,
    bytes on disk for the N steps)."""
    path = workdir / f"crash-{'img' if shape.images else 'arm'}"
    code = f"from bench.replay_bench import crash_child; crash_child({str(path)!r}, {n}, {shape.images})"
    proc = subprocess.Popen(
        [sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    acked = 0
    for line in proc.stdout:  # kill it once about half is acknowledged: mid-stream, a commit may be in flight
        if line.strip() == "done":
            break
        acked = int(line)
        if acked >= n // 2:
            break
    proc.kill()
    proc.wait(timeout=30)
    steps = to_steps(make_episodes(shape, n, seed=1))
    store = open_store(path, map_size_for(shape, n))
    try:
        kept_steps = int(store.stats()["steps"])
        lost = max(0, acked - kept_steps)  # acked steps are a prefix of the stream
        stored, _dups = store.put_steps(steps)  # the edge re-sends everything it has not seen acked
        duplicates = int(store.stats()["steps"]) - len(steps)  # a step stored twice would show here
        if stored + kept_steps != len(steps):
            raise RuntimeError(f"kept {kept_steps} + stored {stored} != {len(steps)}")
        return acked, kept_steps, lost, duplicates, int(store.stats()["bytes_on_disk"])
    finally:
        store.close()


# --------------------------------------------------------------------------- driver


def bench_shape(
    shape: Shape,
    n: int,
    sample_repeats: int,
    workdir: Path,
    log: Callable[..., None],
    encoding: str = "",
    hot_fraction: float = 1.0,
    crash: bool = True,
    edge_jpeg: bool = False,
) -> list[Row]:
    """Ours and the peer take turns (a batch of inserts, a sample) so background load hits both alike.

    encoding: replay.image_encoding for the cameras (the hot tier then keeps them encoded too);
    hot_fraction: the hot tier holds this share of the N transitions (the rest is read from LMDB);
    edge_jpeg: the frames arrive JPEG-encoded by the edge (replay stores and keeps them as sent; the peer gets
    the same raw frames as float32, as its actor sends them); the edge's encode cost is a row of its own.
    """
    episodes = make_episodes(shape, n)
    steps = to_steps(episodes)
    warm_steps = to_steps(episodes, robot_id="warm-0")
    edge_rows: list[Row] = []
    if edge_jpeg:
        steps, enc_s, enc_frames = edge_encode(steps)
        warm_steps = edge_encode(warm_steps)[0]
        check_s, check_frames = replay_check_seconds(steps)
    peer_in = peer_transitions(episodes)  # same transitions, same order
    config = [f"{encoding} in LMDB and hot tier"] if encoding else []
    config += [f"JPEG q{EDGE_JPEG_QUALITY} encoded on the edge, kept as sent"] if edge_jpeg else []
    config += [f"hot tier = N/{round(1 / hot_fraction)}"] if hot_fraction < 1 else []
    group = f"replay {shape.name}, N={n}" + "".join(f", {c}" for c in config)
    tag = f"-{encoding}" if encoding else "-edgejpeg" if edge_jpeg else ""
    path = workdir / (("img" if shape.images else "arm") + tag + f"-{hot_fraction}")
    path.mkdir(parents=True, exist_ok=True)
    # Both sides are timed in their steady state, full and overwriting. Theirs: a ring preallocated with
    # torch.empty, filled once untimed (the first fill pays page faults), then overwritten. Ours, alike:
    # hot tier and byte capacity sized for N, filled once untimed by another robot, whose episodes the
    # timed pass evicts (oldest first) while LMDB reuses their pages.
    store = open_store(
        path, map_size_for(shape, 2 * n), cache_mb=0, image_encoding={"*": encoding} if encoding else None
    )
    stored = [store._stored_form(st) for st in steps[:EPISODE_LEN]]  # the bytes LMDB keeps (encoded or raw)
    per_step = sum(len(st.SerializeToString()) + 40 for st in stored) / len(stored)
    store.capacity_bytes = math.ceil(1.1 * n * per_step)
    frame = sum(a.nbytes for a in episodes[0].observations[0].values())
    if encoding or edge_jpeg:  # the hot tier sizes its rings for encoded frames as 1/8 of raw (hot.ENCODED_GUESS):
        # size it the same way, so every transition is hot (with the JPEG's real size only ~60% were)
        from services.replay.hot import ENCODED_GUESS

        frame = STATE_DIM * 4 + len(CAMERAS) * (IMAGE_HW * IMAGE_HW * 3 // ENCODED_GUESS + 33)
    store.hot_bytes = int(hot_fraction * 1.05 * n * (frame * 9 / 8 + ACTION_DIM * 4 + 48))
    insert_ours(store, warm_steps)
    buf = make_peer(n)
    for tr in peer_in:
        buf.add(**tr)
    try:
        ours_s = peer_s = 0.0
        for i in range(0, n, TURN):
            end = i + TURN
            ours_s += timed(lambda i=i, end=end: insert_ours(store, steps[i:end]))[0]
            peer_s += timed(lambda i=i, end=end: [buf.add(**tr) for tr in peer_in[i:end]])[0]
        have = store.transitions_for(["arm-0"])
        if have != n or len(buf) != n:
            raise RuntimeError(f"ours holds {have}, theirs {len(buf)} transitions; inserted {n}")
        log(f"replay {shape.name}: inserted {n}: ours {ours_s:.2f} s, theirs {peer_s:.2f} s")
        rng = np.random.default_rng(0)
        ours_ms, peer_ms = [], []
        for r in range(sample_repeats + 1):  # round 0 is a warm-up
            o = repeat_ms(lambda: store.sample(BATCH, rng, robot_ids=["arm-0"]), 1, warmup=0)
            p = repeat_ms(lambda: buf.sample(BATCH), 1, warmup=0)
            if r:
                ours_ms += o
                peer_ms += p
        peer_bytes = peer_nbytes(buf) / n
        ours_ram = ours_resident_bytes(store) / n
        hit = store.cache_info()
        st = store.stats()
        disk_per_step = st["bytes_on_disk"] / max(1, st["steps"])
    finally:
        store.close()
    if crash:
        acked, kept, lost, dups, on_disk = crash_survival(workdir, shape, n)
        ours_disk = on_disk / n
    else:
        ours_disk = disk_per_step
    frames = f" ({encoding or 'jpeg'} frames)" if encoding or edge_jpeg else " (uint8 frames)" if shape.images else ""
    if edge_jpeg:
        raw_frame = IMAGE_HW * IMAGE_HW * 3
        jpeg_bytes = sum(len(t.data) for st in steps for t in st.observation.tensors.values()) - n * STATE_DIM * 4
        edge_rows = [
            Row(
                group,
                "edge JPEG encode per frame (robot PC, off the control loop)",
                enc_s / enc_frames * 1e6,
                "none (sends float32)",
                "us",
                None,
                f"cv2.imencode q{EDGE_JPEG_QUALITY} of {enc_frames} {IMAGE_HW}x{IMAGE_HW}x3 frames, one thread; "
                f"{raw_frame} B raw -> {jpeg_bytes / (2 * n):.0f} B mean; paid on the edge, not by replay",
            ),
            Row(
                group,
                "replay's check per JPEG frame (part of Insert validation)",
                check_s / check_frames * 1e6,
                "none",
                "us",
                None,
                "header (H, W) = declared shape and a 1/8-scale grey decode (wire.check_image); not in the insert "
                "row: the 'through replay's Insert loop' group measures inserts with all validation",
            ),
        ]
    rows = [
        Row(
            group,
            "insert",
            n / ours_s,
            n / peer_s,
            "tr/s",
            True,
            f"ours: requests of {BATCH} steps, a window of {IN_FLIGHT} unacked, group-committed, acked after fsync, "
            f"+ hot tier, turns of {TURN} steps; theirs: add() into a warm RAM ring",
        ),
        Row(
            group,
            f"sample batch {BATCH} (median of {sample_repeats})",
            median(ours_ms),
            median(peer_ms),
            "ms",
            False,
            f"ours: hot-tier column gather{' + decode on a thread pool' if encoding or edge_jpeg else ''} (hit rate "
            f"{hit['hits'] / max(1, hit['hits'] + hit['misses']):.0%}, misses read from LMDB); theirs: tensor index",
        ),
        Row(
            group,
            "resident bytes per 1000 transitions",
            ours_ram * 1000,
            peer_bytes * 1000,
            "B",
            False,
            "ours: hot-tier columns + index" + frames + "; theirs: tensors" + (" (images f32)" if shape.images else ""),
        ),
        Row(
            group,
            "bytes per transition",
            ours_disk,
            peer_bytes,
            "B",
            False,
            "ours: LMDB pages on disk (durable); theirs: RAM tensors (lost on exit)",
        ),
    ]
    rows[1:1] = edge_rows
    if crash:
        rows.append(
            Row(
                group,
                "after SIGKILL + restart",
                f"{n + dups}/{n} after re-send; acked lost {lost}, duplicates {dups}",
                f"0/{n} (RAM only)",
                note=f"writer SIGKILLed mid-ingest after {acked} acked ({kept} on disk at restart); "
                f"then all {n} re-sent",
            )
        )
    return rows


# --------------------------------------------------------------------------- through the Insert path


class _StreamContext:
    """What the servicer's Insert loop needs of a gRPC context: abort (a refused step ends the stream) and
    is_active (a cancelled client frees the stream's thread; this one never goes away)."""

    def abort(self, code: Any, details: str) -> None:
        raise RuntimeError(f"{code}: {details}")

    def is_active(self) -> bool:
        return True


def camera_spec(robot_id: str) -> Any:
    from user.v1 import robot_pb2
    from user.v1 import tensor_pb2 as tpb

    features = [robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[STATE_DIM])]
    features += [
        robot_pb2.FeatureSpec(name=f"camera.{c}", dtype=tpb.DTYPE_UINT8, shape=[IMAGE_HW, IMAGE_HW, 3]) for c in CAMERAS
    ]
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="bench_camera_arm",
        action=robot_pb2.ActionSpace(shape=[ACTION_DIM], low=[-1.0] * 3, high=[1.0] * 3, dtype=tpb.DTYPE_FLOAT32),
        observation=features,
        control_rate_hz=10,
        max_episode_steps=EPISODE_LEN,
    )


def insert_streams(servicer: Any, streams: list[list[step_pb2.Step]]) -> None:
    """Each list of steps through the service's Insert loop as its gRPC server runs it, one stream per thread: the
    stream's reader thread checks every JPEG (wire.check_image), the stream thread runs validate_step and the
    episode guard and submits batches to the group-committing writer while it validates the next, acks come after
    the commit. No transport (the peer has none either)."""
    import threading

    from services.replay.server import _Inbox
    from user.v1 import replay_pb2

    errors: list[BaseException] = []

    def run(steps: list[step_pb2.Step]) -> None:
        try:
            requests = (replay_pb2.InsertRequest(seq=i, step=st) for i, st in enumerate(steps))
            inbox = _Inbox(requests, maxsize=2 * servicer.commit_max_steps)
            acked = sum(len(ack.seqs) for ack in servicer._insert(inbox, _StreamContext()))
            inbox.close()
            if acked != len(steps):
                raise RuntimeError(f"{acked} of {len(steps)} steps acked")
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(steps,)) for steps in streams]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]


def bench_camera_service(
    n: int, sample_repeats: int, workdir: Path, log: Callable[..., None], decoded_fraction: float = 0.3
) -> list[Row]:
    """Camera-like frames JPEG-encoded on the edge, inserted through the service's Insert loop with its validation
    (1 stream = one robot, 2 streams = two robots, as the gRPC server runs them in parallel); LMDB and the hot tier
    keep the JPEGs as sent, and the newest `decoded_fraction` of the frames is kept decoded once sampled
    (replay.decoded_mb). Rounds alternate 1 and 2 streams, each with fresh robots inserting all N transitions
    (the buffer evicts the previous round's), and the peer adds the same N transitions after each."""
    from services.replay.hot import ENCODED_GUESS
    from services.replay.server import ReplayServicer
    from services.replay.tables import Draw

    episodes = make_episodes(CAMERA, n)
    peer_in = peer_transitions(episodes)
    rounds = [1, 2, 1, 2]
    plans = []  # per round: the steps of each stream, edge-encoded before timing
    for r, k in enumerate(rounds):
        robots = [f"arm-{r}-{j}" for j in range(k)]
        plans.append([edge_encode(to_steps(episodes[j::k], robot_id=robots[j]))[0] for j in range(k)])
    warm_steps = edge_encode(to_steps(episodes, robot_id="warm-0"))[0]
    path = workdir / f"img-service-{decoded_fraction}"
    path.mkdir(parents=True, exist_ok=True)
    store = open_store(path, map_size_for(CAMERA, 3 * n), cache_mb=0)
    per_step = sum(st.ByteSize() + 40 for st in warm_steps[:EPISODE_LEN]) / EPISODE_LEN
    store.capacity_bytes = math.ceil(1.1 * n * per_step)
    raw_frame = len(CAMERAS) * IMAGE_HW * IMAGE_HW * 3
    # every transition hot: rings sized as the hot tier sizes them (encoded frames guessed at 1/8 of raw); RAM is
    # counted from the bytes really held
    guess = STATE_DIM * 4 + raw_frame // ENCODED_GUESS + len(CAMERAS) * 33
    store.hot_bytes = int(1.05 * n * (guess * 9 / 8 + ACTION_DIM * 4 + 48))
    frames = n + math.ceil(n / EPISODE_LEN)  # every transition's observation + each episode's final one
    store.decoded_bytes = int(decoded_fraction * frames * raw_frame)
    specs = {r: camera_spec(r) for plan in plans for steps in plan for r in {steps[0].robot_id}} | {
        "warm-0": camera_spec("warm-0")
    }
    servicer = ReplayServicer(store, specs.get, commit_max_steps=256, commit_max_delay_s=0.02)
    group = (
        f"replay {CAMERA.name}, N={n}, JPEG q{EDGE_JPEG_QUALITY} from the edge through replay's Insert loop, "
        f"decoded window {decoded_fraction:.0%} of the frames"
    )
    buf = make_peer(n)
    for tr in peer_in:
        buf.add(**tr)
    ours_s = {1: 0.0, 2: 0.0}
    peer_s = {1: 0.0, 2: 0.0}
    try:
        insert_streams(servicer, [warm_steps])
        for k, plan in zip(rounds, plans, strict=True):
            ours_s[k] += timed(lambda plan=plan: insert_streams(servicer, plan))[0]
            peer_s[k] += timed(lambda: [buf.add(**tr) for tr in peer_in])[0]
        robots = [steps[0].robot_id for steps in plans[-1]]
        if store.transitions_for(robots) != n or len(buf) != n:
            raise RuntimeError(f"ours holds {store.transitions_for(robots)}, theirs {len(buf)}; inserted {n}")
        per_kind = {k: rounds.count(k) * n for k in ours_s}
        log(f"{group}: insert ours {ours_s}, theirs {peer_s} s")
        rng = np.random.default_rng(0)
        recent = Draw(batch_size=BATCH, robot_ids=robots, sampler="recency", window=int(decoded_fraction * n))
        ours_ms: dict[str, list[float]] = {"uniform": [], "recency": []}
        peer_ms: list[float] = []
        first_ms = repeat_ms(lambda: store.sample(BATCH, rng, robot_ids=robots), 1, warmup=0)[0]
        shares = {}
        for name, draw in (("uniform", None), ("recency", recent)):
            before = store.cache_info()
            for _ in range(sample_repeats):
                ours_ms[name] += repeat_ms(lambda d=draw: store.sample(BATCH, rng, robot_ids=robots, draw=d), 1, 0)
                peer_ms += repeat_ms(lambda: buf.sample(BATCH), 1, warmup=0)
            after = store.cache_info()
            hits, misses = (after[k] - before[k] for k in ("decoded_hits", "decoded_misses"))
            shares[name] = hits / max(1, hits + misses)
        info = store.cache_info()
        ours_ram = (info["bytes"] + 200 * n) / n
        peer_bytes = peer_nbytes(buf) / n
        window_frames = store._groups[0].decoded_capacity
        st = store.stats()
        disk = st["bytes_on_disk"] / max(1, st["steps"])
    finally:
        store.close()
    log(
        f"{group}: sample ours { {k: round(median(v), 1) for k, v in ours_ms.items()} } ms (first {first_ms:.1f}), "
        f"theirs {median(peer_ms):.1f} ms; decoded-window share {shares}"
    )
    rows = [
        Row(
            group,
            f"insert incl. validation, {k} stream{'s' * (k > 1)} ({k} robot{'s' * (k > 1)})",
            per_kind[k] / ours_s[k],
            per_kind[k] / peer_s[k],
            "tr/s",
            True,
            f"ours: ReplayServicer._insert per stream (JPEG check of every frame in its reader thread, validate_step, "
            f"episode guard, batches of 256 group-committed, acked after fsync), {k} stream(s); theirs: add() into "
            "a warm RAM ring",
        )
        for k in (1, 2)
    ]
    rows += [
        Row(
            group,
            f"sample batch {BATCH}, {name} (median of {sample_repeats})",
            median(ours_ms[name]),
            median(peer_ms),
            "ms",
            False,
            f"ours: {what}; frames of the decoded window copied ({shares[name]:.0%} of distinct frames), the rest "
            f"decoded from JPEG on 2 threads; the first uniform sample after the inserts took {first_ms:.0f} ms; "
            "theirs: uniform, tensor index",
            extra={"first_sample_ms": first_ms, "decoded_window_frames": window_frames, "decoded_share": shares[name]},
        )
        for name, what in (
            ("uniform", "uniform over all N"),
            ("recency", f"recency sampler, the newest {decoded_fraction:.0%} of N"),
        )
    ]
    rows += [
        Row(
            group,
            "resident bytes per 1000 transitions",
            ours_ram * 1000,
            peer_bytes * 1000,
            "B",
            False,
            "ours: hot-tier columns (JPEG bytes of every frame + the decoded window as uint8) + index; theirs: "
            "tensors (images f32)",
        ),
        Row(group, "bytes per transition", disk, peer_bytes, "B", False, "ours: LMDB pages on disk; theirs: RAM"),
    ]
    return rows


def bench_larger_than_hot(n: int, repeats: int, workdir: Path, log: Callable[..., None]) -> list[Row]:
    """State-only buffer 10x the hot tier: uniform draws mostly read LMDB, a recency window stays in RAM."""
    from services.replay.tables import Draw

    episodes = make_episodes(SIM_ARM, n, seed=2)
    steps = to_steps(episodes)
    path = workdir / "cold"
    store = open_store(path, map_size_for(SIM_ARM, n))
    store.hot_bytes = (n // 10) * (STATE_DIM * 4 * 9 // 8 + ACTION_DIM * 4 + 24)  # hot tier: 1/10 of the buffer
    buf = make_peer(n)
    for tr in peer_transitions(episodes):
        buf.add(**tr)
    group = f"replay sim-arm, N={n}, hot tier = N/10"
    rows = []
    try:
        insert_ours(store, steps)
        rng = np.random.default_rng(0)
        peer_ms = repeat_ms(lambda: buf.sample(BATCH), repeats)
        for name, draw in (
            ("uniform over all", None),
            ("recency window N/10", Draw(batch_size=BATCH, sampler="recency", window=n // 10)),
        ):
            before = store.cache_info()
            ms = repeat_ms(lambda draw=draw: store.sample(BATCH, rng, draw=draw), repeats)
            after = store.cache_info()
            hits, misses = after["hits"] - before["hits"], after["misses"] - before["misses"]
            rate = hits / max(1, hits + misses)
            log(f"{group}: {name}: {median(ms):.2f} ms, hit rate {rate:.0%}")
            rows.append(
                Row(
                    group,
                    f"sample batch {BATCH}, {name} (median of {repeats})",
                    median(ms),
                    median(peer_ms),
                    "ms",
                    False,
                    f"ours: hot-tier hit rate {rate:.0%} (hits from RAM, misses from LMDB); theirs: all in RAM",
                    extra={"hit_rate": rate},
                )
            )
    finally:
        store.close()
    return rows


# --------------------------------------------------------------------------- replay -> a learner on its host


def _serve_replay(cfg_json: str, conn: Any) -> None:
    """Child process: a replay service knowing the bench robot's spec; sends its address, stops on any message."""
    from services.replay.server import ReplayService
    from user.config import StackConfig

    specs = {"feed-0": camera_spec("feed-0")}
    service = ReplayService(StackConfig.model_validate_json(cfg_json), spec_source=specs.get, start_metrics=False)
    conn.send(service.start().address)
    conn.recv()
    service.stop()


def _feed_config(path: Path, map_size_mb: int) -> Any:
    """A stack config for a bench replay process at `path` (ephemeral ports, a bench token)."""
    from user.config import StackConfig

    cfg = StackConfig.model_validate({"auth": {"token": "bench-token"}})
    rc = cfg.replay
    rc.server.port = rc.server.metrics_port = 0
    rc.path, rc.map_size_mb = path, map_size_mb
    return cfg


@contextlib.contextmanager
def _replay_process(cfg: Any, steps: list[step_pb2.Step]) -> Iterator[Any]:
    """A replay service in its own (spawned) process, as a learner on another process sees it, holding `steps`
    (sent through its Insert stream): yields its stub; the process stops on exit."""
    import multiprocessing

    from user.rpc import make_channel
    from user.v1 import replay_pb2, replay_pb2_grpc

    ctx = multiprocessing.get_context("spawn")
    to_child, child_end = ctx.Pipe()
    child = ctx.Process(target=_serve_replay, args=(cfg.model_dump_json(), child_end), daemon=True)
    child.start()
    try:
        if not to_child.poll(120):
            raise RuntimeError("replay process did not start")
        with make_channel(to_child.recv(), cfg.auth) as channel:
            stub = replay_pb2_grpc.ReplayStub(channel)
            requests = (replay_pb2.InsertRequest(seq=i, step=st) for i, st in enumerate(steps))
            for _ack in stub.Insert(requests, timeout=600):
                pass
            yield stub
    finally:
        to_child.send("stop")
        child.join(60)


def bench_learner_feed(n: int, seconds: float, rounds: int, workdir: Path, log: Callable[..., None]) -> list[Row]:
    """Batches of 256 with two raw 128x128 cameras (~50 MB) from a replay service in its own process to this one,
    ready as the learner's sampler thread hands them on (decode_arrays): through shared memory (its default on one
    host) vs through the gRPC socket, in alternating windows; and lerobot's in-RAM sample of the same transitions."""
    from cloud_learner.learner import decode_arrays
    from cloud_learner.replay_shm import SharedMemoryReplay, SharedSample
    from user.v1 import replay_pb2

    cfg = _feed_config(workdir / "feed" / "replay", map_size_for(IMAGES, 2 * n))
    rc = cfg.replay
    rc.cache_mb = 2 * n * len(CAMERAS) * IMAGE_HW * IMAGE_HW * 3 >> 20  # every transition in the RAM tier
    shm_dir = Path(tempfile.mkdtemp(prefix="user-bench-", dir="/dev/shm" if Path("/dev/shm").is_dir() else None))
    rc.shm_dir = str(shm_dir)
    episodes = make_episodes(IMAGES, n)
    group = f"replay Sample to a learner on its host, batch {BATCH}, two {IMAGE_HW}x{IMAGE_HW} cameras + state (N={n})"
    try:
        with _replay_process(cfg, to_steps(episodes, "feed-0")) as stub:
            shared = SharedMemoryReplay(stub, str(shm_dir))
            request = replay_pb2.SampleRequest(batch_size=BATCH)
            keys = ["camera.front", "camera.wrist", "state"]
            ways = {
                "shm": lambda: shared.Sample(request, timeout=60),
                "socket": lambda: stub.Sample(request, timeout=60),
            }
            if not isinstance(ways["shm"](), SharedSample):
                raise RuntimeError("replay did not offer shared memory on its own host")
            rates: dict[str, list[float]] = {"shm": [], "socket": []}
            nbytes = 0
            for r in range(rounds):
                for way in ("shm", "socket") if r % 2 == 0 else ("socket", "shm"):
                    done, start = 0, time.perf_counter()
                    while time.perf_counter() - start < seconds:
                        arrays = decode_arrays(ways[way]().batch, keys)
                        done += 1
                    rates[way].append(done / (time.perf_counter() - start))
                    nbytes = sum(
                        a.nbytes for part in ("observation", "next_observation") for a in arrays[part].values()
                    )
            log(f"{group}: batches/s {rates}")
    finally:
        shutil.rmtree(shm_dir, ignore_errors=True)
        shutil.rmtree(workdir / "feed", ignore_errors=True)
    buf = make_peer(n)
    for tr in peer_transitions(episodes):
        buf.add(**tr)
    peer_ms = median(repeat_ms(lambda: buf.sample(BATCH), max(5, rounds * 3), warmup=1))
    shm, sock = median(rates["shm"]), median(rates["socket"])
    note = f"{nbytes / 1e6:.0f} MB of frames a batch; medians of {rounds} alternating {seconds:.0f} s windows"
    return [
        Row(
            group,
            "batches/s ready in the learner, shared memory vs socket",
            shm,
            sock,
            "batches/s",
            True,
            note,
            peer_name="ours through the gRPC socket",
        ),
        Row(
            group,
            "batches/s ready in the learner vs lerobot's in-RAM sample",
            shm,
            1e3 / peer_ms,
            "batches/s",
            True,
            "theirs: ReplayBuffer.sample in the learner's own process, no transport",
            peer_name="lerobot 0.6.1 ReplayBuffer",
        ),
        Row(
            group,
            "batches/s through the socket vs lerobot's in-RAM sample",
            sock,
            1e3 / peer_ms,
            "batches/s",
            True,
            "a learner on another host",
            peer_name="lerobot 0.6.1 ReplayBuffer",
        ),
    ]


def bench_remote_feed(
    n: int, seconds: float, rounds: int, workdir: Path, log: Callable[..., None], link: str = ""
) -> list[Row]:
    """A learner on another host (no shared memory): batches of 256 with two camera-like 128x128 frames, JPEG from
    the edge, through the gRPC socket until decode_arrays hands them on: frames as replay keeps them
    (SampleRequest.encoded_frames, the learner's default; its sampler threads decode) vs decoded by replay (replay's
    default config: no decoded window), in alternating windows."""
    from cloud_learner.learner import decode_arrays
    from user.v1 import replay_pb2

    cfg = _feed_config(workdir / "remote" / "replay", map_size_for(CAMERA, 2 * n))
    cfg.replay.shm_dir = None
    steps = edge_encode(to_steps(make_episodes(CAMERA, n), "feed-0"))[0]
    group = (
        f"replay Sample to a learner on another host (socket{link}), batch {BATCH}, two {IMAGE_HW}x{IMAGE_HW} "
        f"camera-like frames JPEG q{EDGE_JPEG_QUALITY} from the edge (N={n})"
    )
    keys = ["camera.front", "camera.wrist", "state"]
    rates: dict[str, list[float]] = {"kept": [], "decoded": []}
    wire_mb: dict[str, float] = {}
    try:
        with _replay_process(cfg, steps) as stub:
            asks = {way: replay_pb2.SampleRequest(batch_size=BATCH, encoded_frames=way == "kept") for way in rates}
            for way, ask in asks.items():  # what each way puts on the link
                wire_mb[way] = stub.Sample(ask, timeout=60).batch.ByteSize() / 1e6
            for r in range(rounds):
                for way in ("kept", "decoded") if r % 2 == 0 else ("decoded", "kept"):
                    done, start = 0, time.perf_counter()
                    while time.perf_counter() - start < seconds:
                        arrays = decode_arrays(stub.Sample(asks[way], timeout=60).batch, keys)
                        done += 1
                    if arrays["observation"]["camera.front"].shape != (BATCH, IMAGE_HW, IMAGE_HW, 3):
                        raise RuntimeError(f"{way}: frames of the wrong shape")
                    rates[way].append(done / (time.perf_counter() - start))
            log(f"{group}: batches/s {rates}, MB a batch on the wire {wire_mb}")
    finally:
        shutil.rmtree(workdir / "remote", ignore_errors=True)
    kept, decoded = median(rates["kept"]), median(rates["decoded"])
    note = f"medians of {rounds} alternating {seconds:.0f} s windows; replay and learner share this machine's cores"
    return [
        Row(
            group,
            "batches/s ready in the learner: JPEG as kept (learner decodes) vs decoded by replay",
            kept,
            decoded,
            "batches/s",
            True,
            note,
            peer_name="ours, replay decodes (encoded_frames off)",
        ),
        Row(
            group,
            "MB a batch on the link",
            wire_mb["kept"],
            wire_mb["decoded"],
            "MB",
            False,
            "what a slower link between sites carries per batch",
            peer_name="ours, replay decodes (encoded_frames off)",
        ),
    ]


LINK_NAME = "1 Gbit/s"  # a site's shard to a cloud learner


def remote_feed_over_link(quick: bool, workdir: Path, log: Callable[..., None]) -> list[Row]:
    """bench_remote_feed with replay and learner in a private network namespace whose 127.0.0.1 is a 1 Gbit/s tc
    tbf link (as bench.weights_link makes its 20 Mbit/s one); one row saying why where it cannot be made."""
    from bench.netns import link_rows, tbf_setup

    args = ["bench.replay_bench", "--link-child", str(workdir)] + (["--quick"] if quick else [])
    setup = tbf_setup("1gbit", burst="1mb", latency="100ms", mtu=None)
    return link_rows(setup, args, f"replay Sample to a learner on another host over a {LINK_NAME} link", log)


def _link_child(workdir: Path, quick: bool) -> None:
    from bench.netns import emit_rows

    rows = bench_remote_feed(
        200 if quick else 2_000,
        1.0 if quick else 5.0,
        2 if quick else 4,
        workdir,
        lambda *a, **_: print("LOG", *a, flush=True),
        link=f" over a {LINK_NAME} link, tc tbf in a netns",
    )
    emit_rows(rows)


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    workdir.mkdir(parents=True, exist_ok=True)
    sizes = [(SIM_ARM, 600, 3), (IMAGES, 300, 2)] if quick else [(SIM_ARM, 20_000, 30), (IMAGES, 1_000, 10)]
    rows: list[Row] = []
    for shape, n, repeats in sizes:
        rows += bench_shape(shape, n, repeats, workdir, log)
    # camera configs for resident memory: JPEG frames kept encoded (camera-like images; noise does not compress),
    # and raw frames with a hot tier a tenth of the buffer (the rest read from LMDB)
    n_img, r_img = (100, 2) if quick else sizes[1][1:]
    rows += bench_shape(CAMERA, n_img, r_img, workdir, log, encoding="jpeg", crash=False)
    # the same camera-like frames JPEG-encoded on the edge (edge.robots[i].image_encoding): replay stores and keeps
    # the bytes as sent, the sampler decodes
    rows += bench_shape(CAMERA, n_img, r_img, workdir, log, crash=False, edge_jpeg=True)
    rows += bench_shape(IMAGES, n_img, r_img, workdir, log, hot_fraction=0.1, crash=False)
    # the same edge JPEGs through replay's Insert loop (validation included), the newest 30% of the frames kept
    # decoded (RAM <= 1/10 of the peer's), and all of them (uniform draws without decoding, 3-4x less RAM)
    for fraction in (0.3, 1.0):
        rows += bench_camera_service(n_img, r_img, workdir, log, decoded_fraction=fraction)
    rows += bench_larger_than_hot(2_000 if quick else 50_000, 3 if quick else 20, workdir, log)
    rows += bench_learner_feed(200 if quick else 2_000, 2.0 if quick else 5.0, 2 if quick else 4, workdir, log)
    rows += bench_remote_feed(200 if quick else 2_000, 1.0 if quick else 5.0, 2 if quick else 4, workdir, log)
    rows += remote_feed_over_link(quick, workdir, log)
    return rows


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "--link-child":
        _link_child(Path(sys.argv[2]), "--quick" in sys.argv)
