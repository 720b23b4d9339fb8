"""Learner and inference processes register with control like edges register robots: their host, CPU count,
GPUs with memory, the device they compute on and what they serve, re-sent as a heartbeat. Operators see
the GPU pool beside the robots (`userctl workers ls`, Control.ListWorkers).

Never raises into the service once started: control being away only delays the report. A config that cannot
make a channel (no token, an unreadable TLS file) raises ConfigError from start(), in the caller's thread.
"""

from __future__ import annotations

import contextlib
import logging
import os
import platform
import socket
import threading
import time
from collections.abc import Callable, Iterator

import grpc

from user import __version__ as USER_VERSION
from user.config import AuthConfig
from user.log import kv
from user.rpc import Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc

log = logging.getLogger(__name__)

CHANGE_POLL_S = 0.2  # how soon a change of `preparing` is reported (robots waiting for a policy)


def host_devices() -> list[control_pb2.DeviceInfo]:
    """The CPU (host RAM) and every CUDA device torch sees, with its total memory."""
    ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    devices = [control_pb2.DeviceInfo(name="cpu", model=platform.processor() or platform.machine(), memory_bytes=ram)]
    try:
        import torch

        if torch.cuda.is_available():
            for i in range(torch.cuda.device_count()):
                props = torch.cuda.get_device_properties(i)
                devices.append(
                    control_pb2.DeviceInfo(name=f"cuda:{i}", model=props.name, memory_bytes=props.total_memory)
                )
    except Exception as exc:  # a broken driver must not stop the service; it shows as no GPU
        log.warning("cannot list CUDA devices", extra=kv(error=repr(exc)))
    return devices


def worker_info(kind: str, address: str, device: str, experiments: list[str]) -> control_pb2.WorkerInfo:
    host = socket.gethostname()
    return control_pb2.WorkerInfo(
        worker_id=f"{kind}@{host}:{address.rsplit(':', 1)[-1]}",
        kind=kind,
        hostname=host,
        address=address,
        cpu_count=os.cpu_count() or 0,
        devices=host_devices(),
        experiments=experiments,
        software_version=USER_VERSION,
        device=device,
    )


class WorkerReporter:
    """A thread that registers `info()` with control every interval control asks for (at first 10 s)."""

    def __init__(
        self,
        control_addr: str,
        auth: AuthConfig,
        info: Callable[[], control_pb2.WorkerInfo | None],
        timeout_s: float = 5,
    ) -> None:
        self.control_addr, self.auth, self.info, self.timeout_s = control_addr, auth, info, timeout_s
        self.interval_s = 10.0
        self.reported = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="worker-report", daemon=True)
        self._channel: grpc.Channel | None = None

    def start(self) -> WorkerReporter:
        # Here, not in the thread: a missing token must reach the caller as its one-line ConfigError, not
        # as a thread's traceback printed before it.
        self._channel = make_channel(self.control_addr, self.auth)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=self.timeout_s + 1)

    def _run(self) -> None:
        backoff = Backoff(initial_s=0.5, max_s=self.interval_s)
        warned = False
        assert self._channel is not None  # set by start()
        with self._channel as channel:
            stub = control_pb2_grpc.ControlStub(channel)
            while not self._stop.is_set():
                info = self.info()
                if info is None:  # not serving yet
                    self._stop.wait(0.1)
                    continue
                try:
                    resp = stub.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=info), timeout=self.timeout_s)
                except grpc.RpcError as err:
                    if not warned:
                        log.warning("cannot register with control", extra=kv(code=err.code().name))
                        warned = True
                    backoff.sleep(self._stop)
                    continue
                warned = False
                backoff.reset()
                self.reported.set()
                self.interval_s = resp.interval_s if resp.interval_s > 0 else self.interval_s
                self._wait_or_change(info)

    def _wait_or_change(self, sent: control_pb2.WorkerInfo) -> None:
        """Until the next report is due, or earlier when what the learner reports of its robots' experiments
        changed (`preparing`, `failed`, `misfit_robots`: robots hold on them)."""
        due = time.monotonic() + self.interval_s
        while not self._stop.wait(min(CHANGE_POLL_S, max(0.0, due - time.monotonic()))):
            if time.monotonic() >= due:
                return
            now = self.info()
            if now is not None and (now.preparing, now.experiments, now.failed, now.misfit_robots) != (
                sent.preparing,
                sent.experiments,
                sent.failed,
                sent.misfit_robots,
            ):
                return


@contextlib.contextmanager
def report_worker(
    service: object,
    kind: str,
    control_addr: str,
    auth: AuthConfig,
    device: str,
    experiments: Callable[[], list[str]],
    preparing: Callable[[], list[str]] | None = None,
    failed: Callable[[], dict[str, str]] | None = None,
    misfit_robots: Callable[[], dict[str, str]] | None = None,
) -> Iterator[WorkerReporter]:
    """Around `serve_until_signal(service, ...)`: report once the service is bound, until it stops.
    `experiments()`: those it serves (experiments defined at run time join); `preparing()`: the learner's
    experiments without a policy yet (WorkerInfo.preparing); `failed()`: those it cannot train, with why
    (WorkerInfo.failed); `misfit_robots()`: robots that do not fit their experiment's layout, with why
    (WorkerInfo.misfit_robots). All re-read for each report."""

    def info() -> control_pb2.WorkerInfo | None:
        running = getattr(service, "running", None)
        if running is None:
            return None
        names = experiments()
        if getattr(info, "names", None) != names:
            info.cached = worker_info(kind, f"{socket.gethostname()}:{running.port}", device, names)
            info.names = names
        if preparing is None and failed is None and misfit_robots is None:
            return info.cached
        out = control_pb2.WorkerInfo()
        out.CopyFrom(info.cached)
        if preparing is not None:
            out.preparing.extend(preparing())
        if failed is not None:
            out.failed.update(failed())
        if misfit_robots is not None:
            out.misfit_robots.update(misfit_robots())
        return out

    reporter = WorkerReporter(control_addr, auth, info).start()
    try:
        yield reporter
    finally:
        reporter.stop()
