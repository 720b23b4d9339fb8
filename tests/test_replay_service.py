from __future__ import annotations

import grpc
import numpy as np
import pytest

from services.replay.server import ReplayService
from services.replay.store import ReplayStore
from tests.replay_helpers import episode, make_step, spec
from user import wire
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import replay_pb2, replay_pb2_grpc

AUTH = AuthConfig(token="test-token")
SPECS = {"arm-0": spec("arm-0"), "arm-1": spec("arm-1")}


@pytest.fixture
def service(tmp_path):
    cfg = StackConfig(auth=AUTH)
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.server.port = 0
    svc = ReplayService(cfg, spec_source=SPECS.get, start_metrics=False).start()
    yield svc
    svc.stop()


def stub(svc: ReplayService, auth: AuthConfig = AUTH) -> replay_pb2_grpc.ReplayStub:
    return replay_pb2_grpc.ReplayStub(make_channel(svc.address, auth))


def insert(svc, steps, first_seq=0):
    reqs = [replay_pb2.InsertRequest(seq=first_seq + i, step=s) for i, s in enumerate(steps)]
    return list(stub(svc).Insert(iter(reqs), timeout=10))


def stats(svc) -> replay_pb2.StatsResponse:
    return stub(svc).Stats(replay_pb2.StatsRequest(), timeout=5)


def test_acks_follow_commit_and_survive_reopen(service, tmp_path):
    acks = insert(service, episode("arm-0", "e", 40) + episode("arm-1", "f", 10, terminated=True))
    assert sorted(s for a in acks for s in a.seqs) == list(range(50))
    assert sum(a.stored for a in acks) == 50
    service.stop()  # everything acked must be on disk
    store = ReplayStore(tmp_path / "replay", 64)
    assert store.stats()["steps"] == 50 and store.transitions == 50
    store.close()
    service.store = ReplayStore(tmp_path / "replay", 64)  # let the fixture's stop() close something open


def test_resend_is_idempotent(service):
    steps = episode("arm-0", "e", 20)
    insert(service, steps)
    acks = insert(service, steps, first_seq=100)
    assert sorted(s for a in acks for s in a.seqs) == list(range(100, 120))
    assert sum(a.duplicates for a in acks) == 20 and sum(a.stored for a in acks) == 0
    st = stats(service)
    assert st.steps == 20 and st.duplicates == 20


@pytest.mark.parametrize(
    "bad",
    [
        make_step("arm-9", "e", 3),  # unknown robot
        make_step("arm-0", "e", 3, observation=wire.to_tensor_map({"state": np.zeros(5, np.float32)})),
        make_step("arm-0", "e", 3, observation=wire.to_tensor_map({"state": np.full(6, np.nan, np.float32)})),
        make_step("arm-0", "e", 3, action=wire.to_tensor(np.zeros(3, np.int32))),
    ],
    ids=["unknown-robot", "wrong-shape", "nan", "wrong-dtype"],
)
def test_bad_step_is_rejected_and_changes_nothing(service, bad):
    good = episode("arm-0", "e", 3)
    before = stats(service)
    reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate([*good, bad, make_step("arm-0", "e", 4)])]
    acked = []
    with pytest.raises(grpc.RpcError) as err:
        for ack in stub(service).Insert(iter(reqs), timeout=10):
            acked += ack.seqs
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "seq 3" in err.value.details()
    assert acked == [0, 1, 2]  # everything before the bad step was committed and acknowledged
    after = stats(service)
    assert after.steps == before.steps + 3 and after.rejected == before.rejected + 1
    # The service keeps serving.
    insert(service, [make_step("arm-0", "e", 3)], first_seq=10)
    assert stats(service).steps == before.steps + 4


def test_sample_and_its_errors(service):
    with pytest.raises(grpc.RpcError) as err:
        stub(service).Sample(replay_pb2.SampleRequest(batch_size=8), timeout=5)
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    insert(service, episode("arm-0", "e", 10, terminated=True))
    resp = stub(service).Sample(replay_pb2.SampleRequest(batch_size=32), timeout=5)
    assert resp.transitions == 10
    assert wire.from_tensor(resp.batch.observation.tensors["state"]).shape == (32, 6)
    assert wire.from_tensor(resp.batch.policy_version).tolist() == [7] * 32
    with pytest.raises(grpc.RpcError) as err:
        stub(service).Sample(replay_pb2.SampleRequest(batch_size=0), timeout=5)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_missing_token_is_unauthenticated(service):
    anonymous = stub(service, AuthConfig(enabled=False))
    with pytest.raises(grpc.RpcError) as err:
        anonymous.Stats(replay_pb2.StatsRequest(), timeout=5)
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    with pytest.raises(grpc.RpcError) as err:
        list(anonymous.Insert(iter([replay_pb2.InsertRequest(seq=0, step=make_step("arm-0", "e", 0))]), timeout=5))
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert stats(service).steps == 0
