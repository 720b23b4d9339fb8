"""The learner service: SubscribeWeights (weight stream) + GetStatus, with the training loop beside it.

    userctl learner --config configs/demo.yaml

On SIGTERM: stop training, write a final checkpoint, end the weight streams, stop the server.
"""

from __future__ import annotations

import logging

import grpc
import torch

from cloud_learner.learner import Learner
from user import rpc
from user.config import ConfigError, StackConfig
from user.log import kv
from user.policy import check_device
from user.v1 import learner_pb2, learner_pb2_grpc
from user.weights import WeightServicer, WeightStore
from user.worker import report_worker

log = logging.getLogger(__name__)

SERVICE_NAME = learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name


class LearnerServicer(WeightServicer):
    def __init__(self, learner: Learner, store: WeightStore, default_chunk_bytes: int) -> None:
        super().__init__(store, default_chunk_bytes)
        self.learner = learner

    def GetStatus(
        self, request: learner_pb2.LearnerStatusRequest, context: grpc.ServicerContext
    ) -> learner_pb2.LearnerStatus:
        st = self.learner.state
        return learner_pb2.LearnerStatus(
            updates=st.updates,
            weight_version=st.weight_version,
            updates_per_s=st.updates_per_s,
            buffer_transitions=st.buffer_transitions,
            losses=dict(st.losses),
            alpha=st.alpha,
            last_publish_ns=st.last_publish_ns,
            training=self.learner.training,
            subscribers=self.subscribers,
        )


class LearnerService(rpc.GrpcService):
    """In-process learner service (tests, userctl): start() serves and trains, stop() shuts down cleanly."""

    def __init__(self, cfg: StackConfig, start_metrics: bool = True) -> None:
        try:
            check_device(cfg.learner.device)
        except ValueError as exc:
            raise ConfigError(f"learner.device: {exc}") from None
        self.cfg = cfg
        self.start_metrics = start_metrics
        self.store = WeightStore()
        self.learner = Learner(cfg, self.store)
        self.servicer = LearnerServicer(self.learner, self.store, cfg.learner.max_chunk_bytes)
        self.running: rpc.RunningServer | None = None

    def start(self) -> LearnerService:
        torch.set_num_threads(self.cfg.learner.torch_threads)
        self.running = rpc.start_server(
            "learner",
            lambda server: learner_pb2_grpc.add_LearnerServicer_to_server(self.servicer, server),
            [SERVICE_NAME],
            self.cfg.learner.server,
            self.cfg.auth,
            start_metrics=self.start_metrics,
        )
        self.learner.start()
        return self

    def stop(self) -> None:
        self.learner.stop()  # training ends, final checkpoint written
        self.store.close()  # weight streams end cleanly; clients reconnect to the next learner
        if self.running is not None:
            self.running.stop()
            self.running = None


def run(cfg: StackConfig, ready_file: str | None) -> int:
    service = LearnerService(cfg)
    lc = cfg.learner
    with report_worker(service, "learner", lc.control_addr, cfg.auth, lc.device, [lc.robot_kind]):
        rpc.serve_until_signal(service, "learner", ready_file, healthy=lambda: not service.learner.failed)
    if service.learner.failed:
        log.error("learner stopped on an error", extra=kv(error=str(service.learner.error)))
        return 1
    return 0
