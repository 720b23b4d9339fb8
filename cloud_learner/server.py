"""The learner service: SubscribeWeights (weight stream) + GetStatus, with the training loop beside it.

    userctl learner --config configs/demo.yaml

On SIGTERM: stop training, write a final checkpoint, end the weight streams, stop the server.

The learner holds learner.checkpoint_dir (an flock on its owner.lock) from before it reads a checkpoint until its
final checkpoints are written: a second learner on the same directory would publish the same version numbers with
other weights, so it is refused at start (`userctl learner` exits 2 naming the holder's pid).
"""

from __future__ import annotations

import logging
from pathlib import Path

import grpc
import torch

from cloud_learner.checkpoint import CheckpointDirLock, lock_checkpoint_dir, sweep_temp_files
from cloud_learner.learner import ExperimentState, Learner
from user import rpc
from user.config import ConfigError, StackConfig
from user.log import kv
from user.policy import check_device
from user.registry import PluginError
from user.v1 import learner_pb2
from user.weight_shm import ShmWeights
from user.weights import WeightServicer, WeightStore, add_learner_servicer
from user.worker import report_worker

log = logging.getLogger(__name__)

SERVICE_NAME = learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name


class LearnerServicer(WeightServicer):
    def __init__(
        self,
        learner: Learner,
        store: WeightStore,
        default_chunk_bytes: int,
        freshness_s: float,
        shm: ShmWeights | None = None,
    ) -> None:
        super().__init__(store, default_chunk_bytes, freshness_s=freshness_s, shm=shm)
        self.learner = learner

    def unknown_experiment(self, experiment: str) -> str:
        # "" is the first experiment. One defined at run time is known from the learner's next poll of control:
        # a subscriber that asks before then is told NOT_FOUND and retries with its backoff.
        known = self.learner.experiment_states
        if not experiment or experiment in known:
            return ""
        return f"this learner trains no experiment {experiment[:64]!r} (it trains: {', '.join(known) or 'none'})"

    def GetStatus(
        self, request: learner_pb2.LearnerStatusRequest, context: grpc.ServicerContext
    ) -> learner_pb2.LearnerStatus:
        states = list(self.learner.experiment_states.values())
        first = states[0]
        return learner_pb2.LearnerStatus(
            updates=sum(st.updates for st in states),
            weight_version=first.weight_version,
            updates_per_s=sum(st.updates_per_s for st in states),
            buffer_transitions=sum(st.buffer_transitions for st in states),
            losses=dict(first.scalars),
            last_publish_ns=max(st.last_publish_ns for st in states),
            training=self.learner.training,
            subscribers=self.subscribers,
            scalars=dict(first.scalars),
            experiments=[experiment_status(st) for st in states],
            subscriber_status=self.subscriber_status(),  # the console's sync column, per weight stream
        )


def experiment_status(st: ExperimentState) -> learner_pb2.ExperimentStatus:
    return learner_pb2.ExperimentStatus(
        name=st.name,
        algorithm=st.algorithm,
        policy_kind=st.policy_kind,
        updates=st.updates,
        weight_version=st.weight_version,
        updates_per_s=st.updates_per_s,
        buffer_transitions=st.buffer_transitions,
        scalars=dict(st.scalars),
        robot_ids=list(st.robot_ids),
        state=st.state,
        error=st.error,
        sample_errors=st.sample_errors,
        env_steps=st.env_steps,
        waiting_for=st.waiting_for,
    )


def failed_experiments(learner: Learner) -> dict[str, str]:
    """WorkerInfo.failed: experiments this learner cannot train and why, so control's `exp status` / `exp ls`
    do not call an experiment running whose robots are leased while nothing learns from them."""
    return {
        name: st.error or "failed (no reason given)"
        for name, st in learner.experiment_states.items()
        if st.state == "failed"
    }


class LearnerService(rpc.GrpcService):
    """In-process learner service (tests, userctl): start() serves and trains, stop() shuts down cleanly."""

    def __init__(self, cfg: StackConfig, start_metrics: bool = True) -> None:
        try:
            check_device(cfg.learner.device)
        except ValueError as exc:
            raise ConfigError(f"learner.device: {exc}") from None
        self.ckpt_lock = _lock(cfg.learner.checkpoint_dir)  # before any checkpoint is read
        try:
            self._build(cfg, start_metrics)
        except BaseException:
            self.ckpt_lock.release()  # a learner that never started must not keep the directory
            raise

    def _build(self, cfg: StackConfig, start_metrics: bool) -> None:
        sweep_temp_files(cfg.learner.checkpoint_dir)  # under the lock, so no live writer owns them; logs each
        self.cfg = cfg
        self.start_metrics = start_metrics
        self.store = WeightStore(history=cfg.learner.weights_history)
        try:
            self.learner = Learner(cfg, self.store)
        except PluginError as exc:  # a bad experiment entry fails at start, naming the field
            raise ConfigError(str(exc)) from None
        lc = cfg.learner
        # same-host subscribers (inference beside the learner, a stack on one box) read versions from here
        self.shm = ShmWeights(lc.weights_shm_dir) if lc.weights_shm_dir else None
        self.servicer = LearnerServicer(self.learner, self.store, lc.max_chunk_bytes, lc.weights_freshness_s, self.shm)
        self.running: rpc.RunningServer | None = None

    def start(self) -> LearnerService:
        torch.set_num_threads(self.cfg.learner.torch_threads)
        try:
            self.running = rpc.start_server(
                "learner",
                lambda server: add_learner_servicer(self.servicer, server),
                [SERVICE_NAME],
                self.cfg.learner.server,
                self.cfg.auth,
                start_metrics=self.start_metrics,
            )
            self.learner.start()
        except BaseException:
            self.stop()  # e.g. the port is taken: nothing trained, the directory is free for the next try
            raise
        return self

    def stop(self) -> None:
        ended = self.learner.stop()  # training ends, final checkpoints written
        try:
            self.store.close()  # weight streams end cleanly; clients reconnect to the next learner
            if self.shm is not None:
                self.shm.close()  # its version files go with it
            if self.running is not None:
                self.running.stop()
                self.running = None
        finally:
            if ended:
                self.ckpt_lock.release()
            else:  # a thread that may still write keeps it; the kernel drops it when this process exits
                log.error("learner threads still running; learner.checkpoint_dir stays locked until this process exits")


def _lock(checkpoint_dir: Path) -> CheckpointDirLock:
    """The checkpoint directory for this learner alone; one line (ConfigError) when it is in use or cannot be made."""
    try:
        return lock_checkpoint_dir(checkpoint_dir)  # CheckpointDirInUse (a ConfigError) when another learner has it
    except OSError as exc:  # e.g. a read-only or full volume: the service cannot run, say where
        raise ConfigError(f"learner.checkpoint_dir {checkpoint_dir}: {exc.strerror or exc}") from None


def run(cfg: StackConfig, ready_file: str | None) -> int:
    service = LearnerService(cfg)
    lc = cfg.learner

    def experiments() -> list[str]:  # `userctl exp status` lists its learners by these
        return [e.name for e in service.learner.experiments]

    with report_worker(
        service,
        "learner",
        lc.control_addr,
        cfg.auth,
        lc.device,
        experiments,
        service.learner.preparing,
        lambda: failed_experiments(service.learner),
        service.learner.misfit_robots,
    ):
        rpc.serve_until_signal(service, "learner", ready_file, healthy=lambda: not service.learner.failed)
    if service.learner.failed:
        log.error("learner stopped on an error", extra=kv(error=str(service.learner.error)))
        return 1
    return 0
