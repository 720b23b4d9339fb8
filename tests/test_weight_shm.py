"""Same-host weight versions through shared memory: the probe, the round trip, fallbacks, file lifetime.

Real gRPC servers on 127.0.0.1, a tmp dir standing in for /dev/shm."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests import helpers
from tests.test_weight_streams import AUTH, SPEC, Server, tensors, trained
from user.v1 import learner_pb2
from user.v1 import tensor_pb2 as tpb
from user.weight_codec import WE, WeightAssembler
from user.weight_shm import LOCK_SUFFIX, ShmWeights, read_payload
from user.weights import WeightServicer, WeightSet, WeightStore, WeightSubscriber
from user.wire import WireError

SHM = WE.WEIGHT_ENCODING_FP32_SHM
HOST = "test-host-boot-id"


@pytest.fixture
def shm_server(tmp_path: Path) -> Iterator[Server]:
    store = WeightStore()
    shm = ShmWeights(str(tmp_path / "shm"), keep=2, host=HOST)
    (tmp_path / "shm").mkdir()
    srv = Server(store, WeightServicer(store, poll_s=0.1, shm=shm))
    yield srv
    srv.close()
    shm.close()


def subscribe(srv: Server, shm_dir: Path | None, host: str = HOST, **kw) -> tuple[WeightSubscriber, list[WeightSet]]:
    got: list[WeightSet] = []
    sub = WeightSubscriber(
        srv.addr, AUTH, "edge-1", got.append, max_chunk_bytes=4096, shm_dir=str(shm_dir), shm_host=host, **kw
    )
    return sub.start(), got


def same(ws: WeightSet, ref: dict[str, np.ndarray]) -> bool:
    return set(ws.tensors) == set(ref) and all(np.array_equal(ws.tensors[k], ref[k]) for k in ref)


def files(d: Path) -> list[str]:
    """The directory's files but the learners' lock files (each live ShmWeights holds one)."""
    return sorted(p.name for p in d.iterdir() if not p.name.endswith(LOCK_SUFFIX))


def test_shared_memory_round_trip_is_bit_exact_and_acked(shm_server: Server, tmp_path: Path) -> None:
    shm_dir = tmp_path / "shm"
    sub, got = subscribe(shm_server, shm_dir, encoding=WE.WEIGHT_ENCODING_FP32)
    try:
        t = tensors(0)
        for v in (1, 2):
            shm_server.store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            assert got[-1].encoding == SHM and got[-1].encoded_bytes == 0 and same(got[-1], t)
            t = trained(t, v)
        helpers.wait_for(lambda: shm_server.servicer.subscriber_status()[0].applied_version == 2, "ack of v2")
        assert shm_server.servicer.subscriber_status()[0].encoding == SHM
        names = files(shm_dir)  # the probe file is gone; the versions' files are ours, 0600
        assert len(names) == 2 and all("-probe-" not in n for n in names)
        assert all(os.stat(shm_dir / n).st_mode & 0o777 == 0o600 for n in names)
        assert sub.shm_fallbacks == 0 and sub.rejected == 0
    finally:
        sub.stop()


@pytest.mark.parametrize("case", ["other-host", "other-dir", "off"])
def test_a_subscriber_that_is_not_proven_same_host_gets_the_stream(
    shm_server: Server, tmp_path: Path, case: str
) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    if case == "other-host":  # announces another host: no probe at all
        sub, got = subscribe(shm_server, tmp_path / "shm", host="another-boot-id")
    elif case == "other-dir":  # same boot id (a container), but it cannot see our files: the probe fails
        sub, got = subscribe(shm_server, elsewhere)
    else:
        got = []
        sub = WeightSubscriber(shm_server.addr, AUTH, "edge-1", got.append, max_chunk_bytes=4096).start()
    try:
        t = tensors(0)
        shm_server.store.publish(1, SPEC, t)
        assert sub.wait_version(1, 30)
        assert got[-1].encoding != SHM and got[-1].encoded_bytes > 0 and same(got[-1], t)
        assert files(tmp_path / "shm") == [] and files(elsewhere) == []  # no version file, probe removed
    finally:
        sub.stop()


@pytest.mark.parametrize("damage", ["flipped", "truncated", "gone", "symlink"])
def test_a_damaged_file_is_rejected_and_the_version_comes_over_the_stream(
    shm_server: Server, tmp_path: Path, damage: str
) -> None:
    shm_dir = tmp_path / "shm"
    t = tensors(0)
    full = shm_server.store.publish(1, SPEC, t)
    packed = shm_server.servicer._shm_set(full, ("",))  # written before anyone subscribes: we damage it first
    assert packed is not None
    path = shm_dir / packed.header.shm_name
    data = bytearray(path.read_bytes())
    if damage == "flipped":
        data[100] ^= 0xFF
        path.write_bytes(bytes(data))
    elif damage == "truncated":
        path.write_bytes(bytes(data[:-4]))
    elif damage == "gone":
        path.unlink()
    else:
        other = tmp_path / "decoy"
        other.write_bytes(bytes(data))
        path.unlink()
        path.symlink_to(other)
    sub, got = subscribe(shm_server, shm_dir)
    try:
        assert sub.wait_version(1, 30)
        assert sub.shm_fallbacks == 1 and sub.rejected == 1 and sub.connects == 1
        assert len(got) == 1 and got[0].encoding != SHM and same(got[0], t)  # never applied the bad bytes
        t2 = trained(t, 2)
        shm_server.store.publish(2, SPEC, t2)  # the next version goes through shared memory again
        assert sub.wait_version(2, 30)
        assert got[-1].encoding == SHM and same(got[-1], t2)
    finally:
        sub.stop()


def test_old_version_files_are_unlinked_and_close_removes_the_rest(shm_server: Server, tmp_path: Path) -> None:
    shm_dir = tmp_path / "shm"
    sub, got = subscribe(shm_server, shm_dir)
    try:
        t = tensors(0)
        for v in range(1, 6):
            shm_server.store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            t = trained(t, v)
        assert [w.encoding for w in got] == [SHM] * 5
        names = files(shm_dir)
        assert len(names) == 2 and any("-v4-" in n for n in names) and any("-v5-" in n for n in names)
    finally:
        sub.stop()
    shm_server.servicer.shm.close()
    assert files(shm_dir) == []


def test_shared_memory_cap_in_bytes_keeps_the_newest_only(tmp_path: Path) -> None:
    shm = ShmWeights(str(tmp_path), keep=3, max_bytes=3000, host=HOST)
    a = np.zeros(1200, np.uint8)
    first = shm.file_for("a", 1, b"\x01", a)
    second = shm.file_for("b", 1, b"\x02", a)
    assert first and second and len(files(tmp_path)) == 2
    third = shm.file_for("c", 1, b"\x03", a)  # over the cap: the oldest goes, whatever its experiment
    assert files(tmp_path) == sorted([second, third])
    assert shm.file_for("d", 1, b"\x04", np.zeros(4000, np.uint8)) == ""  # bigger than the cap: streamed
    shm.close()
    assert files(tmp_path) == []


@pytest.mark.parametrize(
    "name", ["../user-weights-x", "/etc/passwd", "user-weights-a/../../b", "other-file", "", "user-weights-..x/y"]
)
def test_a_header_naming_a_file_outside_the_shm_dir_is_refused(tmp_path: Path, name: str) -> None:
    h = learner_pb2.WeightHeader(
        version=1, total_bytes=4, digest=b"\0" * 16, digest_kind=learner_pb2.DIGEST_XXH3_128, weight_encoding=SHM
    )
    h.tensors.add(name="w", dtype=tpb.DTYPE_FLOAT32, shape=[1], offset=0, nbytes=4)
    h.shm_name = name
    with pytest.raises(WireError):
        WeightAssembler(str(tmp_path)).feed(learner_pb2.WeightMessage(header=h))
    with pytest.raises(WireError):
        read_payload(str(tmp_path), name, 4, np.empty(4, np.uint8))


def test_a_client_that_asked_for_no_shared_memory_refuses_an_shm_header(tmp_path: Path) -> None:
    h = learner_pb2.WeightHeader(
        version=1, digest=b"\0" * 16, digest_kind=learner_pb2.DIGEST_XXH3_128, weight_encoding=SHM
    )
    h.shm_name = "user-weights-x"
    with pytest.raises(WireError, match="not asked for"):
        WeightAssembler().feed(learner_pb2.WeightMessage(header=h))


def test_files_of_a_learner_that_died_are_swept_at_start(tmp_path: Path) -> None:
    dead = ShmWeights(str(tmp_path), host=HOST)
    name = dead.file_for("a", 1, b"\x01", np.zeros(100, np.uint8))
    gone_pid = 2**22 + 7  # above the kernel's pid_max: no such process
    stale = name.replace(f"-{os.getpid()}-", f"-{gone_pid}-", 1)
    os.rename(tmp_path / name, tmp_path / stale)
    (tmp_path / "unrelated").write_bytes(b"x")
    live = ShmWeights(str(tmp_path), host=HOST)
    assert live.swept == 1
    kept = live.file_for("a", 1, b"\x02", np.zeros(100, np.uint8))
    assert ShmWeights(str(tmp_path), host=HOST).swept == 0  # a live learner's files (this pid) stay
    assert files(tmp_path) == sorted([kept, "unrelated"])
    live.close()


def test_shared_memory_cannot_be_pinned(shm_server: Server) -> None:
    """FP32_SHM is the server's choice after the probe: a request pinning it is refused on both RPCs (found
    by `make fuzz`: it ended in UNKNOWN)."""
    import grpc

    from user import rpc
    from user.v1 import learner_pb2_grpc

    shm_server.store.publish(1, SPEC, tensors(0))
    req = learner_pb2.SubscribeWeightsRequest(client_id="x", encoding=SHM, shm_host=HOST)
    with rpc.make_channel(shm_server.addr, AUTH) as channel:
        stub = learner_pb2_grpc.LearnerStub(channel)
        for call in (
            stub.StreamWeights(iter([learner_pb2.WeightAck(subscribe=req)]), timeout=10),
            stub.SubscribeWeights(req, timeout=10),
        ):
            with pytest.raises(grpc.RpcError) as err:
                next(call)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def big(seed: int) -> dict[str, np.ndarray]:
    return tensors(seed, n=1 << 18)  # 2 MiB of payload: packed into shared-memory buffers (>= MIN_BUFFER_BYTES)


def test_a_payload_packed_in_shared_memory_is_published_by_a_link_not_a_copy(
    shm_server: Server, tmp_path: Path
) -> None:
    shm_dir = tmp_path / "shm"
    sub, got = subscribe(shm_server, shm_dir)
    try:
        t = big(0)
        for v in range(1, 6):  # enough versions for the store's pool to pack into buffers that left
            shm_server.store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            assert got[-1].encoding == SHM and same(got[-1], t)
            t = trained(t, v)
        assert sub.shm_fallbacks == 0 and sub.rejected == 0
        names = files(shm_dir)
        versions = [n for n in names if not n.startswith(".")]
        buffers = {os.stat(shm_dir / n).st_ino for n in names if "-buf-" in n}
        assert len(versions) == 2 and not any("-spare-" in n for n in names)
        for n in versions:  # the payload's own pages under the version's name: a second link, no copy
            st = os.stat(shm_dir / n)
            assert st.st_nlink == 2 and st.st_ino in buffers and st.st_mode & 0o777 == 0o600
    finally:
        sub.stop()
    shm_server.servicer.shm.close()
    assert files(shm_dir) == []  # versions and buffers


def test_a_full_shared_memory_directory_falls_back_to_ordinary_memory_and_copies(
    shm_server: Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("user.weight_shm.os.posix_fallocate", full)
    shm_dir = tmp_path / "shm"
    sub, got = subscribe(shm_server, shm_dir)
    try:
        t = big(0)
        for v in (1, 2):
            shm_server.store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            assert got[-1].encoding == SHM and same(got[-1], t)
            t = trained(t, v)
        names = files(shm_dir)
        assert not any("-buf-" in n for n in names)  # none left behind by the failed tries
        assert all(os.stat(shm_dir / n).st_nlink == 1 for n in names)  # written, not linked
    finally:
        sub.stop()


def test_the_buffer_pool_never_hands_out_a_read_only_buffer() -> None:
    from user.weight_codec import BufferPool

    pool = BufferPool()
    pool.give(np.frombuffer(bytes(2 << 20), np.uint8))  # e.g. a payload that arrived as bytes
    assert pool.take(2 << 20).flags.writeable


def test_a_payload_buffer_leaves_with_its_array_and_frees_its_bytes_under_the_cap(tmp_path: Path) -> None:
    shm = ShmWeights(str(tmp_path), max_bytes=3 << 20, host=HOST)
    first = shm.buffer(2 << 20)
    assert first is not None and first.flags.writeable and len(files(tmp_path)) == 1
    assert shm.buffer(2 << 20) is None  # over the cap: ordinary memory
    assert shm.buffer(1 << 10) is None  # too small to be worth a file
    del first  # the pool let it go
    assert files(tmp_path) == []
    second = shm.buffer(2 << 20)
    assert second is not None
    second[:] = 7
    shm.close()
    assert files(tmp_path) == [] and int(second[-1]) == 7  # unlinked, still mapped until let go


_LEARNER = """
import sys, time
import numpy as np
from user.weight_shm import ShmWeights
shm = ShmWeights(sys.argv[1], host="h")
print(shm.file_for("a", 1, b"\\x01", np.zeros(100, np.uint8)), flush=True)
time.sleep(600)
"""


def test_files_of_a_learner_killed_with_sigkill_are_swept_even_when_its_pid_is_alive(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", _LEARNER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        name = proc.stdout.readline().strip() if proc.stdout else ""
        assert name and (tmp_path / name).exists()
        other = ShmWeights(str(tmp_path), host=HOST)
        assert other.swept == 0 and (tmp_path / name).exists()  # alive: its lock is held
        other.close()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    # its pid may be reused (a restarted container's learner often gets its predecessor's): the lock decides
    os.rename(tmp_path / name, tmp_path / name.replace(f"-{proc.pid}-", f"-{os.getpid()}-", 1))
    for lock in [p for p in tmp_path.iterdir() if p.name.endswith(LOCK_SUFFIX) and f"-{proc.pid}-" in p.name]:
        lock.rename(tmp_path / lock.name.replace(f"-{proc.pid}-", f"-{os.getpid()}-", 1))
    live = ShmWeights(str(tmp_path), host=HOST)
    assert live.swept == 1 and files(tmp_path) == []
    assert [p.name for p in tmp_path.iterdir()] == [f".user-weights-{live.token}{LOCK_SUFFIX}"]  # only ours
    live.close()
    assert list(tmp_path.iterdir()) == []
