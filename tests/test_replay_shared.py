"""Sample batches through shared memory (OpenSharedMemory, SharedBatch): a real replay service over gRPC on
127.0.0.1:0 with LMDB in tmp_path and its slot files in a tmp directory, and the learner's client."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest

from cloud_learner.learner import decode_arrays
from cloud_learner.replay_sampler import SamplerError, replay_source
from cloud_learner.replay_shm import SharedArrays, SharedMemoryReplay, SharedSample
from services.replay import server as replay_server
from services.replay.server import ReplayService
from services.replay.shared import SharedBatches
from tests.test_replay_service import AUTH, _cfg, insert, stub
from user import wire
from user.config import LearnerConfig
from user.rpc import make_channel
from user.shm_files import LOCK_SUFFIX, host_id
from user.v1 import replay_pb2, robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

HW = 8
KEYS = ["camera.front", "state"]


def camera_spec(robot_id: str) -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="test",
        action=robot_pb2.ActionSpace(shape=[3], low=[-1] * 3, high=[1] * 3, dtype=tpb.DTYPE_FLOAT32),
        observation=[
            robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[4]),
            robot_pb2.FeatureSpec(name="camera.front", dtype=tpb.DTYPE_UINT8, shape=[HW, HW, 3]),
        ],
        control_rate_hz=20,
        max_episode_steps=50,
    )


def _obs(t: int) -> tpb.TensorMap:
    return wire.to_tensor_map(
        {"state": np.full(4, t, np.float32), "camera.front": np.full((HW, HW, 3), t % 256, np.uint8)}
    )


def steps(episode: str, length: int) -> list[step_pb2.Step]:
    """Observation t is t everywhere (state and every pixel), reward -t; the final observation is length."""
    out = []
    for t in range(length):
        step = step_pb2.Step(
            robot_id="arm-0",
            episode_id=episode,
            step_index=t,
            observation=_obs(t),
            action=wire.to_tensor(np.full(3, 0.1 * (t % 10), np.float32)),
            reward=-float(t),
            truncated=t == length - 1,
        )
        if t == length - 1:
            step.final_observation.CopyFrom(_obs(t + 1))
        out.append(step)
    return out


@pytest.fixture(autouse=True)
def tiny_batches_through_shared_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests' batches are small (8x8 frames): below replay's SHM_MIN_BYTES they would take the socket."""
    monkeypatch.setattr(replay_server, "SHM_MIN_BYTES", 0)


@pytest.fixture
def shm_dir(tmp_path: Path) -> Path:
    d = tmp_path / "shm"
    d.mkdir()
    return d


@pytest.fixture
def service(tmp_path: Path, shm_dir: Path) -> Iterator[ReplayService]:
    cfg = _cfg(tmp_path / "replay", shm_dir=str(shm_dir), shm_slots=2)
    svc = ReplayService(cfg, spec_source={"arm-0": camera_spec("arm-0")}.get, start_metrics=False).start()
    insert(svc, steps("e1", 30) + steps("e2", 20))
    yield svc
    svc.stop()


def slot_files(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if not p.name.endswith(LOCK_SUFFIX))


def check_rows(arrays: dict) -> None:
    """Every row is one stored transition: observation t, next observation t + 1, reward -t."""
    state, cam = arrays["observation"]["state"], arrays["observation"]["camera.front"]
    t = state[:, 0]
    assert cam.dtype == np.uint8 and cam.shape[1:] == (HW, HW, 3)
    np.testing.assert_array_equal(cam, np.broadcast_to(t[:, None, None, None].astype(np.uint8), cam.shape))
    np.testing.assert_array_equal(arrays["next_observation"]["state"][:, 0], t + 1)
    np.testing.assert_array_equal(arrays["next_observation"]["camera.front"][:, 0, 0, 0], (t + 1).astype(np.uint8))
    np.testing.assert_array_equal(arrays["reward"], -t)
    np.testing.assert_allclose(arrays["action"][:, 0], 0.1 * (t % 10), rtol=1e-6)


def test_batches_come_through_shared_memory_and_match_the_socket(service: ReplayService, shm_dir: Path) -> None:
    client = SharedMemoryReplay(stub(service), str(shm_dir))
    request = replay_pb2.SampleRequest(batch_size=64)
    for _ in range(6):  # more batches than slots: each one's slot is released by the next request
        resp = client.Sample(request, timeout=10)
        assert isinstance(resp, SharedSample) and isinstance(resp.batch, SharedArrays)
        assert resp.transitions == 50
        check_rows(decode_arrays(resp.batch, KEYS))
    assert service.shared is not None and service.shared.sessions() == 1
    assert len(slot_files(shm_dir)) <= 2  # slots are reused; the probe went at the first sample
    over_socket = stub(service).Sample(request, timeout=10)
    assert not over_socket.HasField("shared")
    inline = decode_arrays(over_socket.batch, KEYS)
    check_rows(inline)
    shared = decode_arrays(client.Sample(request, timeout=10).batch, KEYS)
    for part in ("observation", "next_observation"):
        for key in KEYS:
            assert shared[part][key].dtype == inline[part][key].dtype
            assert shared[part][key].shape == inline[part][key].shape
    assert sorted(shared) == sorted(inline)


def test_a_batch_still_held_is_never_overwritten_by_a_later_one(service: ReplayService, shm_dir: Path) -> None:
    """Batches are read into reused buffers (>= 1 MiB each): one is reused only once no array of it is alive."""
    client = SharedMemoryReplay(stub(service), str(shm_dir))
    request = replay_pb2.SampleRequest(batch_size=4096)  # ~1.8 MB: pooled
    held = []
    for i in range(6):
        arrays = decode_arrays(client.Sample(request, timeout=10).batch, KEYS)
        if i % 2 == 0:  # every other batch is dropped at once: its buffer may serve the next
            held.append((arrays, {k: v.copy() for k, v in arrays["observation"].items()}))
    for arrays, as_received in held:
        check_rows(arrays)
        for key, value in as_received.items():
            np.testing.assert_array_equal(arrays["observation"][key], value)


def test_a_learner_holding_every_slot_gets_the_socket_and_keeps_its_session(
    service: ReplayService, shm_dir: Path
) -> None:
    client = SharedMemoryReplay(stub(service), str(shm_dir))
    request = replay_pb2.SampleRequest(batch_size=16)
    held = [client.Sample(request, timeout=10) for _ in range(2)]  # the fixture's 2 slots, both still viewed
    assert all(isinstance(r, SharedSample) for r in held)
    over_socket = client.Sample(request, timeout=10)
    assert isinstance(over_socket, replay_pb2.SampleResponse) and over_socket.shm_reason == "no free slot"
    del held  # the learner trained on them: their slots go back with the next request
    assert isinstance(client.Sample(request, timeout=10), SharedSample)


@pytest.mark.parametrize("small", [False, True])
def test_after_replay_restarts_the_learner_opens_a_new_session(
    tmp_path: Path, shm_dir: Path, monkeypatch: pytest.MonkeyPatch, small: bool
) -> None:
    import cloud_learner.replay_shm as sampler

    monkeypatch.setattr(sampler, "REOPEN_S", 0.0)
    if small:  # every batch takes the socket; the session is still checked, and renewed
        monkeypatch.setattr(replay_server, "SHM_MIN_BYTES", 1 << 40)
    cfg = _cfg(tmp_path / "replay", shm_dir=str(shm_dir))
    specs = {"arm-0": camera_spec("arm-0")}.get
    svc = ReplayService(cfg, spec_source=specs, start_metrics=False).start()
    insert(svc, steps("e1", 10))
    port = svc.address.rsplit(":", 1)[1]
    client = SharedMemoryReplay(stub(svc), str(shm_dir))
    request = replay_pb2.SampleRequest(batch_size=8)
    first = client.Sample(request, timeout=10)
    assert isinstance(first, replay_pb2.SampleResponse if small else SharedSample)
    session = client._nonce
    assert session
    svc.stop()
    cfg.replay.server.port = int(port)
    svc = ReplayService(cfg, spec_source=specs, start_metrics=False).start()
    try:
        again = client.Sample(request, timeout=10)  # the old session is unknown: this batch through the socket
        assert isinstance(again, replay_pb2.SampleResponse) and again.shm_reason == "unknown session"
        then = client.Sample(request, timeout=10)  # a new session
        assert isinstance(then, replay_pb2.SampleResponse if small else SharedSample)
        assert client._nonce and client._nonce != session
        del first  # the old session's slot, held until now, is unmapped once free (its file is gone)
        client.Sample(request, timeout=10)
        assert all(m.session == client._nonce for m in client._mapped.values())
    finally:
        svc.stop()


def test_a_lost_answer_moves_the_learner_to_a_new_session_and_the_old_one_idles_out(
    service: ReplayService, shm_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Replay filled a slot for an answer the learner never got (its deadline passed): that slot would stay taken,
    so the learner starts a new session; the old one's files go once it idles out."""
    import services.replay.shared as shared

    real = stub(service)
    answers = {"lose": True}

    class LossyStub:
        def __getattr__(self, name: str) -> Any:
            return getattr(real, name)

        def Sample(self, request: replay_pb2.SampleRequest, timeout: float) -> Any:
            resp = real.Sample(request, timeout=timeout)
            if answers.pop("lose", False) and resp.HasField("shared"):
                raise SamplerError(grpc.StatusCode.DEADLINE_EXCEEDED, "answer lost")
            return resp

    client = SharedMemoryReplay(LossyStub(), str(shm_dir))
    request = replay_pb2.SampleRequest(batch_size=16)
    with pytest.raises(grpc.RpcError):
        client.Sample(request, timeout=10)
    lost_session = next(iter(service.shared._sessions))  # type: ignore[union-attr]
    assert isinstance(client.Sample(request, timeout=10), SharedSample)  # a new session at once
    assert service.shared.sessions() == 2  # type: ignore[union-attr]
    lost_files = [shm_dir / s.name for s in service.shared._sessions[lost_session].slots.values()]  # type: ignore
    assert lost_files and all(f.exists() for f in lost_files)
    service.shared._sessions[lost_session].last_used -= shared.IDLE_S + 1  # type: ignore[union-attr]
    monkeypatch.setattr(service.shared, "_expired_at", 0.0)
    assert isinstance(client.Sample(request, timeout=10), SharedSample)  # sampling expires idle sessions
    assert lost_session not in service.shared._sessions  # type: ignore[union-attr]
    assert service.shared.sessions() == 1 and not any(f.exists() for f in lost_files)  # type: ignore[union-attr]


def test_a_slot_replay_cannot_fill_sends_the_batch_through_the_socket(
    service: ReplayService, shm_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    client = SharedMemoryReplay(stub(service), str(shm_dir))
    assert isinstance(client.Sample(replay_pb2.SampleRequest(batch_size=8), timeout=10), SharedSample)

    def broken(*_: Any) -> Any:
        raise RuntimeError("no slot today")

    monkeypatch.setattr(service.shared, "write", broken)
    resp = client.Sample(replay_pb2.SampleRequest(batch_size=8), timeout=10)  # not UNKNOWN: the socket
    assert isinstance(resp, replay_pb2.SampleResponse) and resp.shm_reason == "error"
    check_rows(decode_arrays(resp.batch, KEYS))


def test_a_small_batch_takes_the_socket_and_the_session_stays(
    service: ReplayService, shm_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    client = SharedMemoryReplay(stub(service), str(shm_dir))
    assert isinstance(client.Sample(replay_pb2.SampleRequest(batch_size=64), timeout=10), SharedSample)
    monkeypatch.setattr(replay_server, "SHM_MIN_BYTES", 256 << 10)
    small = client.Sample(replay_pb2.SampleRequest(batch_size=64), timeout=10)  # ~26 kB
    assert isinstance(small, replay_pb2.SampleResponse) and small.shm_reason == "small batch"
    check_rows(decode_arrays(small.batch, KEYS))
    big = client.Sample(replay_pb2.SampleRequest(batch_size=2048), timeout=10)  # ~850 kB: the same session
    assert isinstance(big, SharedSample)
    assert service.shared is not None and service.shared.sessions() == 1


def test_the_learner_samples_through_shared_memory_by_default(service: ReplayService, shm_dir: Path) -> None:
    lc = LearnerConfig(replay_shm_dir=str(shm_dir))
    with make_channel(service.address, AUTH) as channel:
        source = replay_source(lc, AUTH, channel)
        assert isinstance(source, SharedMemoryReplay)
        assert isinstance(source.Sample(replay_pb2.SampleRequest(batch_size=8), timeout=10), SharedSample)
        assert source.Stats(replay_pb2.StatsRequest(), timeout=10).transitions == 50  # other calls: the stub's
    assert not isinstance(replay_source(LearnerConfig(replay_shm_dir=None), AUTH, channel), SharedMemoryReplay)


def test_a_caller_that_cannot_read_the_directory_gets_the_socket(
    service: ReplayService, shm_dir: Path, tmp_path: Path
) -> None:
    elsewhere = tmp_path / "other-shm"  # e.g. a container with its own /dev/shm
    elsewhere.mkdir()
    client = SharedMemoryReplay(stub(service), str(elsewhere))
    resp = client.Sample(replay_pb2.SampleRequest(batch_size=16), timeout=10)
    assert isinstance(resp, replay_pb2.SampleResponse) and resp.HasField("batch") and not resp.HasField("shared")
    check_rows(decode_arrays(resp.batch, KEYS))
    # a guessed session is not one: the batch comes through the socket
    guessed = stub(service).Sample(replay_pb2.SampleRequest(batch_size=16, shm_session=os.urandom(32)), timeout=10)
    assert not guessed.HasField("shared") and guessed.HasField("batch")


def test_another_host_gets_no_offer(tmp_path: Path) -> None:
    shared = SharedBatches(str(tmp_path), 1 << 20, host="this-host")
    try:
        offer = shared.offer("other-host")
        assert offer.probe_file == "" and "host" in offer.reason
        assert shared.offer("this-host").probe_file
    finally:
        shared.close()
    assert slot_files(tmp_path) == []


def test_a_caller_that_never_releases_gets_the_socket_once_its_slots_are_taken(
    service: ReplayService, shm_dir: Path
) -> None:
    raw = stub(service)
    offer = raw.OpenSharedMemory(replay_pb2.SharedMemoryRequest(host_id=host_id()), timeout=10)
    nonce = (shm_dir / offer.probe_file).read_bytes()
    request = replay_pb2.SampleRequest(batch_size=16, shm_session=nonce)
    first, second = (raw.Sample(request, timeout=10) for _ in range(2))
    assert first.HasField("shared") and second.HasField("shared") and first.shared.file != second.shared.file
    third = raw.Sample(request, timeout=10)  # both slots are the caller's: never overwritten under it
    assert not third.HasField("shared") and third.HasField("batch")
    request.shm_release.append(first.shared.file)
    assert raw.Sample(request, timeout=10).shared.file == first.shared.file


def test_a_replaced_slot_is_refused_and_the_batch_comes_through_the_socket(
    service: ReplayService, shm_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cloud_learner.replay_shm as sampler

    map_slot = sampler.map_slot

    def replaced(directory: str, shared: replay_pb2.SharedBatch) -> Any:
        path = shm_dir / shared.file  # another process of this user put another file under its name
        path.unlink()
        path.write_bytes(b"x" * 10)
        return map_slot(directory, shared)

    monkeypatch.setattr(sampler, "map_slot", replaced)
    client = SharedMemoryReplay(stub(service), str(shm_dir))
    resp = client.Sample(replay_pb2.SampleRequest(batch_size=16), timeout=10)
    assert isinstance(resp, replay_pb2.SampleResponse) and resp.HasField("batch") and not resp.HasField("shared")
    check_rows(decode_arrays(resp.batch, KEYS))


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("shm_session", b"short", "shm_session"),
        ("shm_release", ["../../etc/passwd"], "shm_release"),
        ("shm_release", ["user-replay-x"] * 65, "shm_release"),
    ],
)
def test_bad_shared_memory_fields_are_invalid_argument(service: ReplayService, field: str, value, match: str) -> None:
    request = replay_pb2.SampleRequest(batch_size=4)
    if isinstance(value, list):
        getattr(request, field).extend(value)
    else:
        setattr(request, field, value)
    with pytest.raises(grpc.RpcError) as err:
        stub(service).Sample(request, timeout=10)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and match in err.value.details()
    with pytest.raises(grpc.RpcError) as err:
        stub(service).OpenSharedMemory(replay_pb2.SharedMemoryRequest(host_id="x" * 200), timeout=10)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert stub(service).Stats(replay_pb2.StatsRequest(), timeout=10).transitions == 50  # still serving


def test_slot_files_go_at_stop(tmp_path: Path, shm_dir: Path) -> None:
    cfg = _cfg(tmp_path / "replay", shm_dir=str(shm_dir))
    svc = ReplayService(cfg, spec_source={"arm-0": camera_spec("arm-0")}.get, start_metrics=False).start()
    try:
        insert(svc, steps("e1", 10))
        client = SharedMemoryReplay(stub(svc), str(shm_dir))
        assert isinstance(client.Sample(replay_pb2.SampleRequest(batch_size=4), timeout=10), SharedSample)
        assert slot_files(shm_dir)
    finally:
        svc.stop()
    assert list(shm_dir.iterdir()) == []


_REPLAY = """
import sys, time
import numpy as np
from services.replay.shared import SharedBatches
from user.shm_files import host_id
shared = SharedBatches(sys.argv[1], 1 << 20)
offer = shared.offer(host_id())
nonce = open(sys.argv[1] + "/" + offer.probe_file, "rb").read()
batch, _ = shared.write(nonce, [], {"observation": {}, "next_observation": {}, "action": np.zeros((2, 3), np.float32)})
print(batch.file, flush=True)
time.sleep(600)
"""


def test_slots_of_a_replay_killed_with_sigkill_are_swept_by_the_next(shm_dir: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", _REPLAY, str(shm_dir)], stdout=subprocess.PIPE, text=True)
    try:
        name = proc.stdout.readline().strip() if proc.stdout else ""
        assert name and (shm_dir / name).exists()
        alive = SharedBatches(str(shm_dir), 1 << 20)
        assert alive.owner.swept == 0 and (shm_dir / name).exists()  # its owner lives: its lock is held
        alive.close()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    after = SharedBatches(str(shm_dir), 1 << 20)
    assert after.owner.swept == 1 and slot_files(shm_dir) == []
    after.close()
    assert list(shm_dir.iterdir()) == []
