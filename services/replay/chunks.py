"""Action chunks for sampled rows: the actions of steps t .. t+H-1 of the same episode.

Action-chunking policies (ACT, flow-matching VLAs) learn to predict the next H actions from one
observation. Replay stores one action per step, so a chunk is assembled at sample time by walking
the index's episode links (next_tid) from each sampled transition:

- past the episode's end (or a transition evicted meanwhile) the last real action repeats and
  `chunk_mask` is false there (the loss should skip those);
- a row a human chose (intervention) gets only the human's actions: its chunk ends where the
  intervention ended, since what the policy did next is not a label (HG-DAgger).

Actions are read from the hot tier's rows when they are still there, else from LMDB. Kept apart
from store.py (it reads the store's index and hot groups under the store's lock) so the sample
path needs two lines: `add_action_chunks(store, arrays, horizon)` after `store.sample`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from services.replay.disk import ReplayError
from services.replay.store import ReplayStore, tensor_array
from services.replay.tables import Index
from user.v1 import step_pb2

MAX_ACTION_HORIZON = 256  # actions per chunk; ACT uses 100, pi0 50


def horizon_problem(horizon: int) -> str | None:
    """Why a SampleRequest.action_horizon is invalid (0 and 1 both mean one action per row), or None."""
    if horizon > MAX_ACTION_HORIZON:
        return f"action_horizon must be in 1..{MAX_ACTION_HORIZON}, got {horizon}"
    return None


def chunk_tids(index: Index, tids: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """(B, H) transition ids of each row's chunk (the last real one repeated) and (B, H) bool mask."""
    n = len(tids)
    out = np.empty((n, horizon), np.int64)
    mask = np.zeros((n, horizon), np.bool_)
    out[:, 0], mask[:, 0] = tids, True
    human = index.intervention.a[tids]
    cur = tids.copy()
    going = np.ones(n, np.bool_)
    for h in range(1, horizon):
        going &= ~(index.terminated.a[cur] | index.truncated.a[cur])  # the episode ended at cur
        nxt = index.next_tid.a[cur]
        going &= nxt >= 0
        on = np.flatnonzero(going)
        ok = index.alive.a[nxt[on]] & (~human[on] | index.intervention.a[nxt[on]])
        going[on[~ok]] = False
        cur = np.where(going, nxt, cur)
        out[:, h], mask[:, h] = cur, going
    return out, mask


def gather_actions(store: ReplayStore, tids: np.ndarray, like: np.ndarray) -> np.ndarray:
    """Actions of `tids` (caller holds store._lock), float32 shaped like one row of `like`."""
    idx = store.index
    out = np.empty((len(tids), *like.shape[1:]), np.float32)
    done = np.zeros(len(tids), np.bool_)
    groups, rows = idx.group.a[tids], idx.hot_row.a[tids]
    for gid in np.unique(groups[groups >= 0]).tolist():
        sel = np.flatnonzero(groups == gid)
        hot = store._groups[gid]
        ok = sel[hot.valid(rows[sel], tids[sel])]
        out[ok] = hot.action[rows[ok]].reshape(len(ok), *like.shape[1:])
        done[ok] = True
    cold = np.flatnonzero(~done)
    if len(cold):
        keys = idx.keys_of(tids[cold])
        for i, raw in zip(cold.tolist(), store._get_many(keys), strict=True):
            if raw is None:
                raise ReplayError(f"index points at a missing step {idx.key(int(tids[i]))!r}")
            out[i] = tensor_array(step_pb2.Step.FromString(raw).action).reshape(like.shape[1:])
    return out


def add_action_chunks(store: ReplayStore, arrays: dict[str, Any], horizon: int) -> None:
    """Add `action_chunk` (B, H, A) float32 and `chunk_mask` (B, H) bool to a store.sample() result."""
    if horizon <= 1:
        return
    first = arrays["action"]
    with store._lock:
        store._check_open()
        rows, ok = store.index.rows_of(np.asarray(arrays["indices"], np.int64))
        ids, mask = chunk_tids(store.index, rows, horizon)
        mask[~ok, 1:] = False  # evicted since the sample: its first action only (padded)
        real = mask[:, 1:]
        uniq, inverse = np.unique(ids[:, 1:][real], return_inverse=True)
        actions = gather_actions(store, uniq, first)[inverse] if len(uniq) else None
    chunk = np.empty((len(first), horizon, *first.shape[1:]), np.float32)
    chunk[:, 0] = first
    later = chunk[:, 1:]
    if actions is not None:
        later[real] = actions
    for h in range(1, horizon):  # padding: the last real action repeats (the mask is false from there on)
        pad = ~mask[:, h]
        chunk[pad, h] = chunk[pad, h - 1]
    arrays["action_chunk"] = chunk
    arrays["chunk_mask"] = mask
