"""Weights over a slow link: time-to-fresh with adaptive encoding vs full fp32 resends, at 20 Mbit/s.

The link is emulated in a private network namespace (`unshare -n`): loopback brought up with a
1500-byte MTU and a tc tbf qdisc at 20 Mbit/s, so 127.0.0.1 moves about 19 Mbit/s. The parent
(`run`) starts `python -m bench.weights_link --child` inside it and reads its rows as JSON; where
namespaces or tc are not allowed it returns one row saying the benchmark was skipped and why.

Per version: the learner side takes a few Adam steps on the actor, publishes, and the time until the
subscriber holds the version is measured; the received policy acts on a fixed set of observations and
its largest action deviation from the sender's fp32 policy is recorded.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from bench import Row, median
from bench.netns import child_main, emit_rows

RATE = "20mbit"


def run(quick: bool, log: Callable[..., None] = print) -> list[Row]:
    from bench.netns import SLOW_LINK, link_rows

    args = ["bench.weights_link", "--child"] + (["--quick"] if quick else [])
    return link_rows(SLOW_LINK, args, "weights over 20 Mbit/s (tc tbf in a netns)", log)


def _child(quick: bool) -> None:
    from bench.weights_bench import OursFanout, Trainer, sized_config
    from user.policy import actor_from_config, build_policy, module_tensors, policy_spec_for
    from user.weight_codec import WE, encoding_name
    from user.weights import DEFAULT_KEYFRAME_EVERY

    params = 0.25e6 if quick else 1e6
    versions = 2 if quick else 4
    config = sized_config(params)
    torch.manual_seed(0)
    module = actor_from_config(config)
    spec = policy_spec_for(config)
    obs = {"state": np.random.default_rng(1).standard_normal((256, 64)).astype(np.float32)}
    raw_bytes = sum(t.numel() * t.element_size() for t in module.state_dict().values())
    results: dict[str, dict[str, Any]] = {}
    for side, encoding in (("fp32", WE.WEIGHT_ENCODING_FP32), ("adaptive", WE.WEIGHT_ENCODING_ADAPTIVE)):
        torch.manual_seed(0)
        module = actor_from_config(config)
        trainer = Trainer(module)
        fan = OursFanout(spec, 1, encoding, allow_lossy=True)
        times, devs, encs, sizes = [], [], [], []
        try:
            fan.send(module)  # first version: a full set, which also measures the link
            for _ in range(versions):
                trainer.step()
                seconds, tensors = fan.send(module)
                got = build_policy(spec, tensors, fan.version).act(obs, deterministic=True)
                want = build_policy(spec, module_tensors(module), fan.version).act(obs, deterministic=True)
                times.append(seconds)
                devs.append(float(np.max(np.abs(got - want))))
                encs.append(encoding_name(fan.last_encoding))
                sizes.append(fan.wire_bytes)
        finally:
            fan.close()
        results[side] = {"ms": median(times) * 1e3, "dev": max(devs), "encs": encs, "bytes": median(sizes)}
        print(f"LOG   slow link {side}: {results[side]}", flush=True)
    group = f"weights over {RATE} (tc tbf in a netns), {params / 1e6:.2f}M params, {raw_bytes / 2**20:.1f} MiB"
    a, f = results["adaptive"], results["fp32"]
    rows = [
        Row(
            group,
            f"time-to-fresh (median of {versions})",
            a["ms"],
            f["ms"],
            "ms",
            False,
            f"adaptive ({'/'.join(sorted(set(a['encs'])))}, {a['bytes'] / 2**20:.2f} MiB) vs fp32 resend",
            "fp32 full resend",
        ),
        Row(
            group,
            f"time-to-fresh incl. one exact resync per {DEFAULT_KEYFRAME_EVERY} versions (mean)",
            ((DEFAULT_KEYFRAME_EVERY - 1) * a["ms"] + f["ms"]) / DEFAULT_KEYFRAME_EVERY,
            f["ms"],
            "ms",
            False,
            "the resync costs about one fp32 resend (fp32+zstd)",
            "fp32 full resend",
        ),
        Row(
            group,
            "bytes on the wire per version (median)",
            a["bytes"],
            f["bytes"],
            "B",
            False,
            "time-to-fresh also pays encode/decode on a shared CPU",
            "fp32 full resend",
        ),
        Row(
            group,
            "max action deviation (256 fixed obs)",
            f"{a['dev']:.1e}",
            f"{f['dev']:.1e}",
            note="received policy vs the sender's fp32 policy; target < 1e-2",
            peer_name="fp32 full resend",
        ),
    ]
    emit_rows(rows)


if __name__ == "__main__":
    child_main(_child, run)
