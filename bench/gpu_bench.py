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

import os
import time
from collections.abc import Callable
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
