"""GPU timings (opt-in `--only gpu`; a GPU machine): the learner's algorithms and flow_vla's forward on CUDA vs
the same code on every CPU core of the same machine.

Updates go through the learner's own batch path (`cloud_learner.learner.to_batch`: numpy arrays as replay's
Sample decodes them -> tensors on the device), so host-to-device copies are in the time, as they are in the
learner (there they overlap the previous update: the prefetch thread builds batches ahead). Each case runs for
a fixed time after warm-up, with the device synchronised before the clock stops. Inference: one `Policy.act`
(preprocess: uint8 images and state copied in, resize/normalise on the device; the flow integration; the chunk
back as numpy) at batch 1, 16 and 32, the sizes the inference service's batcher hands the model.

The serving path end to end (gRPC, batching, robots as processes) on the GPU is the inference_vla bench with
`--set inference.device=cuda`.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench import Row

PEER = "the same code on the CPU"
CAMERAS = ("camera.front", "camera.wrist")


@dataclass(frozen=True)
class Case:
    label: str  # what the group name says
    kind: str
    params: dict[str, Any]
    state_dim: int
    action_dim: int
    cameras: int  # 128x128 RGB cameras
    horizon: int = 0  # > 0: action chunks in the batch (flow_bc)


CASES = [
    Case(
        "SAC from state (25-d Panda state, 7-d action), MLP 256x256, 2 critics, batch 256",
        "sac",
        {"batch_size": 256, "hidden": [256, 256], "num_critics": 2},
        25,
        7,
        0,
    ),
    Case(
        "RLPD-style SAC from state, 10 critics with LayerNorm, UTD 4, batch 256",
        "sac",
        {"batch_size": 256, "hidden": [256, 256], "num_critics": 10, "critic_layer_norm": True, "utd": 4},
        25,
        7,
        0,
    ),
    Case(
        "SAC from pixels (two 128x128 cameras + state, DrQ shift, CNN encoder), batch 256",
        "sac",
        {"batch_size": 256, "hidden": [256, 256], "num_critics": 2},
        25,
        7,
        2,
    ),
    Case(
        "flow_bc VLA-sized flow_vla (two 128x128 cameras, hidden 1536, chunk 16x7, 10 flow steps), batch 64",
        "flow_bc",
        {
            "batch_size": 64,
            "horizon": 16,
            "hidden": 1536,
            "image_size": 128,
            "flow_steps": 10,
            "tables": {"online": 1.0},
            "human_only": False,
        },
        15,
        7,
        2,
        16,
    ),
]


def layout_of(case: Case) -> Any:
    from cloud_learner.algorithm import Feature, Layout

    observation = {"state": Feature((case.state_dim,), "float32")}
    observation |= {k: Feature((128, 128, 3), "uint8", True) for k in CAMERAS[: case.cameras]}
    ones = np.ones(case.action_dim, np.float32)
    return Layout(observation, -ones, ones, ("arm",))


def arrays(case: Case, layout: Any, seed: int) -> dict[str, Any]:
    """One batch as replay's Sample decodes it (numpy; images uint8)."""
    rng = np.random.default_rng(seed)
    n = int(case.params["batch_size"])

    def obs() -> dict[str, np.ndarray]:
        out = {}
        for k, f in layout.observation.items():
            shape = (n, *f.shape)
            out[k] = rng.integers(0, 256, shape, dtype=np.uint8) if f.is_image else rng.normal(size=shape)
            out[k] = out[k].astype(f.dtype)
        return out

    batch: dict[str, Any] = {
        "observation": obs(),
        "next_observation": obs(),
        "action": rng.uniform(-1, 1, (n, case.action_dim)).astype(np.float32),
        "reward": rng.normal(size=n).astype(np.float32),
        "terminated": (rng.random(n) < 0.05).astype(np.float32),
        "intervention": rng.random(n) < 0.5,
    }
    if case.horizon:
        batch["action_chunk"] = rng.uniform(-1, 1, (n, case.horizon, case.action_dim)).astype(np.float32)
        batch["chunk_mask"] = np.ones((n, case.horizon), bool)
    return batch


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def rate(step: Callable[[int], Any], device: str, seconds: float, warmup: int = 3) -> tuple[float, int]:
    """(calls per second, calls) of step(i) run for about `seconds` after `warmup` calls."""
    for i in range(warmup):
        step(i)
    _sync(device)
    calls, start = 0, time.perf_counter()
    while True:
        step(calls)
        calls += 1
        if calls % 4 == 0 or not device.startswith("cuda"):  # let the GPU queue work; check the clock now and then
            _sync(device)
            if time.perf_counter() - start >= seconds:
                break
    return calls / (time.perf_counter() - start), calls


def update_rate(case: Case, device: str, seconds: float) -> tuple[float, int]:
    from cloud_learner.algorithm import ALGORITHMS
    from cloud_learner.learner import to_batch

    layout = layout_of(case)
    algo = ALGORITHMS.build(case.kind, case.params, layout=layout, device=torch.device(device))
    pool = [arrays(case, layout, seed) for seed in range(4)]
    return rate(lambda i: algo.update(to_batch(pool[i % 4], device)), device, seconds)


def act_rate(batch: int, device: str, seconds: float) -> tuple[float, int]:
    from bench.inference_vla_bench import VLA, make_weights
    from user.policy import build_policy

    weights = make_weights(VLA)
    policy = build_policy(weights.policy, weights.tensors, 1, device)
    rng = np.random.default_rng(0)
    obs = {k: rng.integers(0, 256, (batch, 128, 128, 3), dtype=np.uint8) for k in VLA.cameras}
    obs["state"] = rng.normal(size=(batch, 15)).astype(np.float32)
    texts = ["reach the red target"] * batch
    return rate(lambda _: policy.forward(policy.preprocess(obs, texts), True), device, seconds)


def publish_ms(params: float, device: str, repeats: int) -> float:
    """Median ms the learner's training thread spends publishing a version of a `params`-parameter actor trained on
    `device`: the algorithm's policy() copy to host numpy (`user.policy.module_tensors`: pinned buffers and one
    wait on a GPU) plus `WeightStore.publish` (the pack subscribers are served from), as `cloud_learner.learner`
    does every publish_every updates. An Adam step before each version, so the copy waits for queued work as in
    training."""
    from bench.weights_bench import sized_config
    from user.policy import actor_from_config, module_tensors, policy_spec_for
    from user.weights import WeightStore

    config = sized_config(params)
    actor = actor_from_config(config).to(device)
    opt = torch.optim.Adam(actor.parameters(), lr=1e-4)
    obs = torch.randn(256, config["obs_dim"], device=device)
    spec, store = policy_spec_for(config), WeightStore()
    times = []
    for version in range(1, repeats + 2):
        _, _, action = actor(obs)
        opt.zero_grad()
        action.square().mean().backward()
        opt.step()  # queued, not waited for: publish's copy waits, as after a learner update
        start = time.perf_counter()
        store.publish(version, spec, module_tensors(actor))
        if version > 1:  # the first pays one-off allocations
            times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times))


def _spec(case: Case) -> Any:
    from user.v1 import robot_pb2
    from user.v1 import tensor_pb2 as tpb

    spec = robot_pb2.RobotSpec(robot_id="bench-0", kind="gpu_bench", control_rate_hz=20, max_episode_steps=100)
    spec.action.shape.append(case.action_dim)
    spec.action.low.extend([-1.0] * case.action_dim)
    spec.action.high.extend([1.0] * case.action_dim)
    spec.observation.add(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[case.state_dim])
    for key in CAMERAS[: case.cameras]:
        spec.observation.add(name=key, dtype=tpb.DTYPE_UINT8, shape=[128, 128, 3], is_image=True)
    return spec


def _steps(case: Case, episodes: int, length: int) -> Iterator[Any]:
    """Random transitions as an edge sends them (raw uint8 frames)."""
    from user import wire
    from user.v1 import replay_pb2, step_pb2

    rng = np.random.default_rng(0)

    def obs() -> Any:
        features: dict[str, np.ndarray] = {"state": rng.normal(size=case.state_dim).astype(np.float32)}
        for key in CAMERAS[: case.cameras]:
            features[key] = rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)
        return wire.to_tensor_map(features)

    seq = 0
    for e in range(episodes):
        for t in range(length):
            step = step_pb2.Step(
                robot_id="bench-0",
                episode_id=f"e{e}",
                step_index=t,
                observation=obs(),
                action=wire.to_tensor(rng.uniform(-1, 1, case.action_dim).astype(np.float32)),
                reward=float(rng.normal()),
                truncated=t == length - 1,
            )
            if t == length - 1:
                step.final_observation.CopyFrom(obs())
            yield replay_pb2.InsertRequest(seq=seq, step=step)
            seq += 1


def _loop_seconds(experiment: str) -> dict[str, float]:
    from prometheus_client import REGISTRY

    out = {}
    for phase in ("update", "wait_batch", "publish", "capped"):
        value = REGISTRY.get_sample_value("user_learner_loop_seconds_total", {"experiment": experiment, "phase": phase})
        out[phase] = value or 0.0
    return out


def _serve_replay(cfg_json: str, conn: Any) -> None:
    """Child process: a replay service for the pipeline rows; sends its address, stops on any message."""
    from services.replay.server import ReplayService
    from user.config import StackConfig

    service = ReplayService(StackConfig.model_validate_json(cfg_json), start_metrics=False).start()
    conn.send(service.address)
    conn.recv()
    service.stop()


def pipeline_rate(case: Case, device: str, seconds: float, workdir: Path, transitions: int = 2000) -> dict[str, float]:
    """The learner service on `device` (this process) training from a real replay service (its own process) over
    loopback gRPC, control giving the robot's spec: updates/s once training runs, the training thread's time by
    phase."""
    import queue as queue_module

    from cloud_learner.server import LearnerService
    from services.control.server import ControlService
    from user.config import StackConfig
    from user.rpc import make_channel
    from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc, replay_pb2_grpc

    name = f"bench-{case.kind}-{case.cameras}"
    cfg = StackConfig.model_validate(
        {
            "auth": {"token": "bench-token"},
            "experiments": [
                {
                    "name": name,
                    "robots": {"kinds": ["gpu_bench"]},
                    "algorithm": {"kind": case.kind, "params": case.params},
                }
            ],
        }
    )
    for section in (cfg.control, cfg.replay, cfg.learner):
        section.server.port, section.server.metrics_port, section.server.grace_s = 0, 0, 0.5
    cfg.replay.path, cfg.replay.map_size_mb = workdir / name / "replay", 4096
    lc = cfg.learner
    lc.device, lc.checkpoint_dir, lc.min_transitions = device, workdir / name / "ckpt", 100
    lc.publish_every, lc.checkpoint_every, lc.max_updates_per_transition = 100, 10**9, 1e6
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = lc.control_addr = control.address
    up: queue_module.Queue = queue_module.Queue()
    register = control_pb2.RegisterRequest(agent_id="gpu-bench", hostname="bench", robots=[_spec(case)])
    up.put(control_pb2.EdgeMessage(register=register))
    link = control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth)).Connect(iter(up.get, None))
    next(link)  # registered
    # Replay in its own process, as deployed: its Sample assembly must not share the learner's GIL.
    ctx = multiprocessing.get_context("spawn")
    to_replay, replay_end = ctx.Pipe()
    replay = ctx.Process(target=_serve_replay, args=(cfg.model_dump_json(), replay_end), daemon=True)
    replay.start()
    if not to_replay.poll(120):
        raise RuntimeError("replay process did not start")
    lc.replay_addr = to_replay.recv()
    learner = None
    try:
        stub = replay_pb2_grpc.ReplayStub(make_channel(lc.replay_addr, cfg.auth))
        length = 100
        for _ack in stub.Insert(_steps(case, max(1, transitions // length), length), timeout=600):
            pass
        learner = LearnerService(cfg, start_metrics=False).start()
        status = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))

        def updates() -> int:
            exps = status.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10).experiments
            return int(exps[0].updates) if exps else 0

        deadline = time.monotonic() + 300
        while updates() < 20 and time.monotonic() < deadline:
            time.sleep(0.2)
        u0, p0, t0 = updates(), _loop_seconds(name), time.perf_counter()
        time.sleep(seconds)
        u1, p1, t1 = updates(), _loop_seconds(name), time.perf_counter()
    finally:
        if learner is not None:
            learner.stop()
        to_replay.send("stop")
        replay.join(30)
        up.put(None)
        link.cancel()
        control.stop()
    spent = {k: p1[k] - p0[k] for k in p0}
    return {"updates_per_s": (u1 - u0) / (t1 - t0), **{f"{k}_share": v / (t1 - t0) for k, v in spent.items()}}


def _not_run(why: str) -> list[Row]:
    return [Row("gpu timings", "CUDA device", "not run", why, peer_name=PEER)]


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    if not torch.cuda.is_available():
        return _not_run("torch sees no CUDA device here")
    device = "cuda"
    name = torch.cuda.get_device_name(0)
    cores = os.cpu_count() or 1
    threads = torch.get_num_threads()
    torch.set_num_threads(cores)  # the peer gets every core of the machine
    seconds = 1.0 if quick else 6.0
    rows: list[Row] = []
    try:
        for case in CASES[:1] if quick else CASES:
            log(f"gpu: {case.label}")
            gpu, n_gpu = update_rate(case, device, seconds)
            cpu, n_cpu = update_rate(case, "cpu", seconds)
            rows.append(
                Row(
                    f"learner update, {case.label}",
                    f"updates/s, {name} vs {cores} CPU cores",
                    gpu,
                    cpu,
                    "updates/s",
                    True,
                    f"{n_gpu} / {n_cpu} updates timed; host-to-device copies of each batch included",
                    peer_name=PEER,
                )
            )
        for case in [CASES[0]] if quick else [CASES[0], CASES[2]]:
            log(f"gpu: learner service from replay, {case.label}")
            alone, _ = update_rate(case, device, seconds)
            served = pipeline_rate(case, device, 2 * seconds, workdir, 500 if quick else 2000)
            rows.append(
                Row(
                    f"learner service on {name} sampling a replay service over loopback gRPC, {case.label}",
                    "updates/s, fed by replay vs fed from memory",
                    served["updates_per_s"],
                    alone,
                    "updates/s",
                    True,
                    f"training thread: update {served['update_share']:.0%}, waiting for a batch "
                    f"{served['wait_batch_share']:.0%}, publish {served['publish_share']:.0%} of the window",
                    peer_name="the same algorithm fed from memory (no replay, no gRPC)",
                )
            )
        for params in (1e6,) if quick else (1e6, 25e6):
            log(f"gpu: publish {params / 1e6:.0f}M params")
            repeats = 3 if quick else 10
            try:  # new and not yet run on a GPU: a failure here must not cost the other rows
                gpu, cpu = publish_ms(params, device, repeats), publish_ms(params, "cpu", repeats)
            except Exception as exc:
                log(f"gpu: publish {params / 1e6:.0f}M failed: {exc!r}")
                rows.append(Row(f"weights published from a learner on {name}", "ms per version", "failed", repr(exc)))
                continue
            rows.append(
                Row(
                    f"weights published from a learner on {name}, {params / 1e6:.0f}M-param actor (issue 8's GPU path)",
                    f"ms per version on the training thread, {name} vs {cores} CPU cores",
                    gpu,
                    cpu,
                    "ms",
                    False,
                    f"median of {repeats}; device -> pinned host copy, one wait, WeightStore pack; an Adam step queued "
                    "before each",
                    peer_name=PEER,
                )
            )
        for batch in (1,) if quick else (1, 16, 32):
            log(f"gpu: flow_vla act, batch {batch}")
            gpu, _ = act_rate(batch, device, seconds / 2)
            cpu, _ = act_rate(batch, "cpu", seconds / 2)
            rows.append(
                Row(
                    "flow_vla act (13.9M params, two 128x128 cameras, chunk 16x7, 10 flow steps)",
                    f"batch {batch}: ms per call, {name} vs {cores} CPU cores",
                    1e3 / gpu,
                    1e3 / cpu,
                    "ms",
                    False,
                    f"{batch * gpu:.0f} vs {batch * cpu:.0f} chunks/s; preprocess + forward + chunk back to numpy",
                    peer_name=PEER,
                )
            )
    finally:
        torch.set_num_threads(threads)
    return rows
