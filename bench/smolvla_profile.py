"""Where SmolVLA's forward time goes on a GPU, at smolvla_base's size: batch 1 and 16, wall and CPU ms, the
number of GPU kernels and their busy time (`python -m bench.smolvla_profile` on a CUDA machine)."""

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.inference_vla_bench import SMOLVLA, smolvla_weights
from user.policy import build_policy


def main() -> None:
    torch.set_float32_matmul_precision("high")
    weights = smolvla_weights(SMOLVLA, Path(tempfile.mkdtemp()) / "smolvla")
    policy = build_policy(weights.policy, weights.tensors, 1, "cuda")
    for batch in (1, 16):
        obs = {
            "camera.front": np.zeros((batch, 128, 128, 3), np.uint8),
            "camera.wrist": np.zeros((batch, 128, 128, 3), np.uint8),
            "state": np.zeros((batch, 15), np.float32),
        }
        prepared = policy.preprocess(obs, ["reach the red target"] * batch)
        policy.forward(prepared)
        torch.cuda.synchronize()
        start, cpu = time.perf_counter(), time.process_time()
        for _ in range(3):
            policy.forward(prepared)
        torch.cuda.synchronize()
        wall, cpu = (time.perf_counter() - start) / 3 * 1e3, (time.process_time() - cpu) / 3 * 1e3
        print(f"smolvla batch {batch}: forward {wall:.1f} ms wall, {cpu:.1f} ms CPU", flush=True)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            policy.forward(prepared)
            torch.cuda.synchronize()
        events = prof.key_averages()
        kernels = sum(e.count for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
        gpu_ms = sum(e.self_device_time_total for e in events) / 1e3
        print(f"smolvla batch {batch}: {kernels} GPU kernels, {gpu_ms:.1f} ms GPU busy", flush=True)


if __name__ == "__main__":
    main()
