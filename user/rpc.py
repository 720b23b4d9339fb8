"""Everything a USER gRPC process shares: token auth, metrics, health, reflection, TLS,
graceful shutdown, client channels with auth and keepalive, and reconnect backoff.

A service is `start_server(...)` + `wait_for_shutdown(...)`; a client is `make_channel(...)`.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import random
import re
import signal
import socket
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from concurrent import futures
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import prometheus_client
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from user.auth import AuthError, AuthTable, Identity
from user.config import AuthConfig, ConfigError, ServerConfig

log = logging.getLogger(__name__)

AUTH_HEADER = "authorization"
# Health checks and reflection stay open so orchestrators and grpcurl work without the token.
OPEN_METHOD_PREFIXES = ("/grpc.health.v1.Health/", "/grpc.reflection.")
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
CHANNEL_OPTIONS = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", 10_000),
    ("grpc.keepalive_timeout_ms", 5_000),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.max_pings_without_data", 0),
    # gRPC's own reconnect backoff grows to 120 s by default, so a client would stay cut off
    # long after a restarted server is back; cap it (our Backoff paces the retries above it).
    ("grpc.initial_reconnect_backoff_ms", 200),
    ("grpc.min_reconnect_backoff_ms", 200),
    ("grpc.max_reconnect_backoff_ms", 2_000),
]
SERVER_OPTIONS = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", 10_000),
    ("grpc.keepalive_timeout_ms", 5_000),
    ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.so_reuseport", 0),
]

RPC_TOTAL = prometheus_client.Counter(
    "user_grpc_server_handled_total", "RPCs handled, by method and status code", ["method", "code"]
)
RPC_SECONDS = prometheus_client.Histogram(
    "user_grpc_server_handling_seconds",
    "RPC handling time (streams: whole stream)",
    ["method"],
    buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1, 5, 30, 300),
)
OPEN_STREAMS = prometheus_client.Gauge(
    "user_grpc_open_streams", "Open streaming RPCs (each holds a handler thread), by method", ["method"]
)
# gRPC sends status details in a trailer: past the peer's metadata limit (16 KiB, 8 KiB soft) the caller gets
# RESOURCE_EXHAUSTED "Stream removed" instead of our status. Percent-encoded, 1000 bytes stay under 3 KiB.
MAX_DETAILS_BYTES = 1000
CLIENT_ERRORS = prometheus_client.Counter(
    "user_grpc_client_errors_total",
    "Failed calls and broken streams seen by this client, by method and code",
    ["method", "code"],
)


# --------------------------------------------------------------------------- server side


def _wrap_handler(handler: grpc.RpcMethodHandler, wrap: Callable[[Callable, bool], Callable]):
    """Rebuild a method handler with its behaviour wrapped (keeps the streaming kind)."""
    if handler.unary_unary:
        return grpc.unary_unary_rpc_method_handler(
            wrap(handler.unary_unary, False), handler.request_deserializer, handler.response_serializer
        )
    if handler.unary_stream:
        return grpc.unary_stream_rpc_method_handler(
            wrap(handler.unary_stream, True), handler.request_deserializer, handler.response_serializer
        )
    if handler.stream_unary:
        return grpc.stream_unary_rpc_method_handler(
            wrap(handler.stream_unary, False), handler.request_deserializer, handler.response_serializer
        )
    return grpc.stream_stream_rpc_method_handler(
        wrap(handler.stream_stream, True), handler.request_deserializer, handler.response_serializer
    )


_CALLERS: dict[int, Identity] = {}  # id(context) -> identity, while the call runs


def at_stream_end(context: grpc.ServicerContext, cleanup: Callable[[], None]) -> Callable[[], None]:
    """Run `cleanup` once, when the RPC ends; returns the once-only call for the handler's own `finally` too.

    A streaming handler's `finally` alone is not enough: when the client cancels while a message is being
    sent, gRPC drops the handler's generator at that yield and neither resumes nor closes it, so code after
    the yield never runs. gRPC's termination callback always does; whichever of the two comes first cleans up."""
    lock = threading.Lock()
    done = False

    def once() -> None:
        nonlocal done
        with lock:
            if done:
                return
            done = True
        cleanup()

    if not context.add_callback(once):  # the RPC has already ended
        once()
    return once


def caller(context: grpc.ServicerContext) -> Identity | None:
    """Who is making this call (None when auth is off): handlers use it to bind an edge to its agent."""
    return _CALLERS.get(id(context))


def auth_table(auth: AuthConfig) -> AuthTable | None:
    """The server's token table: the shared token (admin), the tokens file (roles), or None when auth is off."""
    if not auth.enabled:
        return None
    shared = auth.token or os.environ.get("USER_TOKEN") or None
    if not (shared or auth.token_file or auth.tokens_file):
        auth.resolved_token()  # raises the ConfigError that names the field
    try:
        return AuthTable(shared, auth.token_file, auth.tokens_file)
    except AuthError as exc:
        raise ConfigError(str(exc)) from None


class TokenAuthInterceptor(grpc.ServerInterceptor):
    """Identifies each call by `authorization: Bearer <token>` (or its mTLS certificate) and checks the
    method against the identity's role: UNAUTHENTICATED without a known identity, PERMISSION_DENIED
    when the role may not call the method."""

    def __init__(self, table: AuthTable) -> None:
        self.table = table

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        method = handler_call_details.method
        if handler is None or method.startswith(OPEN_METHOD_PREFIXES):
            return handler
        bearer = str(dict(handler_call_details.invocation_metadata or ()).get(AUTH_HEADER, ""))
        table = self.table

        def check(context: grpc.ServicerContext) -> Identity:
            names = [n.decode(errors="replace") for n in (context.auth_context() or {}).get("x509_common_name", [])]
            ident = table.identify(bearer, names)
            if ident is None:
                context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or invalid token")
            if not ident.may_call(method):
                context.abort(grpc.StatusCode.PERMISSION_DENIED, f"role {ident.role} may not call {method}")
            return ident

        def guard(behavior: Callable, streaming: bool) -> Callable:
            if streaming:

                def run_stream(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
                    _CALLERS[id(context)] = check(context)
                    try:
                        yield from behavior(request, context)
                    finally:
                        _CALLERS.pop(id(context), None)

                return run_stream

            def run_unary(request: Any, context: grpc.ServicerContext) -> Any:
                _CALLERS[id(context)] = check(context)
                try:
                    return behavior(request, context)
                finally:
                    _CALLERS.pop(id(context), None)

            return run_unary

        return _wrap_handler(handler, guard)


def bounded_details(details: str) -> str:
    """Status details cut to MAX_DETAILS_BYTES of UTF-8, saying how much was left out (messages may quote
    client input of any length)."""
    if not isinstance(details, str) or len(details) <= MAX_DETAILS_BYTES // 4:  # 4 bytes a character at most
        return details
    data = details.encode(errors="replace")
    if len(data) <= MAX_DETAILS_BYTES:
        return details
    kept = data[:MAX_DETAILS_BYTES].decode(errors="ignore")
    return f"{kept}... ({len(details) - len(kept)} more characters)"


class _BoundedContext:
    """A handler's ServicerContext whose status details are bounded (bounded_details); all else is the context's."""

    __slots__ = ("_context",)

    def __init__(self, context: grpc.ServicerContext) -> None:
        self._context = context

    def __getattr__(self, name: str) -> Any:
        return getattr(self._context, name)

    def abort(self, code: grpc.StatusCode, details: str) -> None:
        self._context.abort(code, bounded_details(details))

    def abort_with_status(self, status: grpc.Status) -> None:
        self._context.set_trailing_metadata(status.trailing_metadata)
        self.abort(status.code, status.details)

    def set_details(self, details: str) -> None:
        self._context.set_details(bounded_details(details))


def _final_code(context: grpc.ServicerContext, failed: bool) -> str:
    """The status an RPC ended with, as its name: the one the handler set, else CANCELLED (DEADLINE_EXCEEDED)
    when the client went away first (not a handler failure), else UNKNOWN for an exception, else OK."""
    code = context.code()
    if code is None:
        if not context.is_active():
            code = grpc.StatusCode.DEADLINE_EXCEEDED if context.time_remaining() <= 0 else grpc.StatusCode.CANCELLED
        else:
            code = grpc.StatusCode.UNKNOWN if failed else grpc.StatusCode.OK
    return code.name if isinstance(code, grpc.StatusCode) else str(code)


class MetricsInterceptor(grpc.ServerInterceptor):
    """Counts every RPC by final status code and times it; bounds the status details our handlers set."""

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None:
            return handler
        method = handler_call_details.method

        def observe(start: float, context: grpc.ServicerContext, failed: bool) -> None:
            RPC_TOTAL.labels(method, _final_code(context, failed)).inc()
            RPC_SECONDS.labels(method).observe(time.perf_counter() - start)

        def timed(behavior: Callable, streaming: bool) -> Callable:
            if streaming:

                def run_stream(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
                    context, start, failed = _BoundedContext(context), time.perf_counter(), False
                    # counted when the RPC ends too: gRPC drops a cancelled stream's generator at a yield
                    counted = at_stream_end(context, lambda: observe(start, context, failed))
                    try:
                        yield from behavior(request, context)
                    except GeneratorExit:  # closed where gRPC dropped it: the client went away
                        raise
                    except BaseException:
                        failed = True
                        raise
                    finally:
                        counted()

                return run_stream

            def run_unary(request: Any, context: grpc.ServicerContext) -> Any:
                context, start, failed = _BoundedContext(context), time.perf_counter(), False
                try:
                    return behavior(request, context)
                except BaseException:
                    failed = True
                    raise
                finally:
                    observe(start, context, failed)

            return run_unary

        return _wrap_handler(handler, timed)


def stream_limit(max_workers: int) -> int:
    """Streams a server holds open at once: the rest of its handler threads stay for unary calls and health."""
    return max(1, max_workers - max(4, max_workers // 4))


class _StreamSlot:
    """One open stream's place under the limit, given back once: when its handler returns, or when the RPC ends
    while the handler is suspended at a yield (gRPC then frees the thread, and may never resume or close the
    generator). A handler still running after the RPC ended keeps its thread, so it keeps its place too."""

    def __init__(self, give: Callable[[], None]) -> None:
        self._give = give
        self._lock = threading.Lock()
        self._running, self._ended, self._held = True, False, True

    def suspend(self) -> None:
        with self._lock:
            self._running = False
            ended = self._ended
        if ended:
            self.give()

    def resume(self) -> None:
        with self._lock:
            self._running = True

    def rpc_ended(self) -> None:
        with self._lock:
            self._ended = True
            idle = not self._running
        if idle:
            self.give()

    def give(self) -> None:
        with self._lock:
            held, self._held = self._held, False
        if held:
            self._give()


class StreamLimitInterceptor(grpc.ServerInterceptor):
    """Each open stream holds a handler thread: past `stream_limit(max_workers)` open streams a new one is
    refused with RESOURCE_EXHAUSTED, so idle or slow streams never starve unary calls and health checks."""

    def __init__(self, max_workers: int, setting: str) -> None:
        self.max_workers, self.setting = max_workers, setting
        self.limit = stream_limit(max_workers)
        self._open = 0
        self._lock = threading.Lock()

    def _take(self, method: str, context: grpc.ServicerContext) -> _StreamSlot:
        with self._lock:
            full = self._open >= self.limit
            if not full:
                self._open += 1
        if full:
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"{method}: {self.limit} streams are open, the most this server holds ({self.setting} is "
                f"{self.max_workers}; {self.max_workers - self.limit} threads stay for unary calls and health "
                f"checks); retry later, or raise {self.setting}",
            )
        OPEN_STREAMS.labels(method).inc()
        slot = _StreamSlot(lambda: self._give(method))
        if not context.add_callback(slot.rpc_ended):  # the RPC has already ended
            slot.rpc_ended()
        return slot

    def _give(self, method: str) -> None:
        with self._lock:
            self._open -= 1
        OPEN_STREAMS.labels(method).dec()

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None or not (handler.request_streaming or handler.response_streaming):
            return handler
        method = handler_call_details.method

        def limited(behavior: Callable, streaming: bool) -> Callable:
            if streaming:

                def run_stream(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
                    slot = self._take(method, context)
                    try:
                        for response in behavior(request, context):
                            slot.suspend()
                            yield response
                            slot.resume()
                    finally:
                        slot.give()

                return run_stream

            def run_unary(request_iterator: Any, context: grpc.ServicerContext) -> Any:
                slot = self._take(method, context)
                try:
                    return behavior(request_iterator, context)
                finally:
                    slot.give()

            return run_unary

        return _wrap_handler(handler, limited)


@dataclass
class RunningServer:
    name: str
    server: grpc.Server
    port: int
    metrics_port: int
    health: health.HealthServicer
    service_names: list[str]
    grace_s: float
    _metrics_http: Any = None

    def address(self, host: str = "127.0.0.1") -> str:
        return f"{host}:{self.port}"

    def stop(self) -> None:
        """Graceful: report NOT_SERVING, refuse new calls, let calls in flight finish."""
        self.health.enter_graceful_shutdown()
        self.server.stop(self.grace_s).wait()
        if self._metrics_http is not None:
            self._metrics_http.shutdown()
            self._metrics_http.server_close()


_PEM_CERT = b"-----BEGIN CERTIFICATE-----"
_PEM_KEY = re.compile(rb"-----BEGIN (?:(RSA|EC|DSA|ENCRYPTED|OPENSSH) )?PRIVATE KEY-----")


def _read_file(setting: str, path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{setting} {path}: cannot read it ({exc.strerror or exc})") from None


def _pem_certificates(setting: str, path: Path) -> tuple[bytes, list[Any] | None]:
    """The file's bytes, checked to hold PEM certificates; with `cryptography` installed (a dev dependency)
    also parsed, and returned parsed so the key can be matched. Never echoes the file's contents."""
    data = _read_file(setting, path)
    if _PEM_CERT not in data:
        raise ConfigError(f"{setting} {path}: not a PEM certificate (no BEGIN CERTIFICATE block)")
    try:
        from cryptography import x509
    except ImportError:
        return data, None
    try:
        return data, x509.load_pem_x509_certificates(data)
    except ValueError:
        raise ConfigError(f"{setting} {path}: not a valid PEM certificate") from None


def _pem_private_key(setting: str, path: Path) -> tuple[bytes, Any | None]:
    """Like _pem_certificates for an unencrypted PEM private key (gRPC cannot ask for a passphrase)."""
    data = _read_file(setting, path)
    found = _PEM_KEY.search(data)
    if found is None:
        raise ConfigError(f"{setting} {path}: not a PEM private key (no BEGIN PRIVATE KEY block)")
    if found.group(1) == b"ENCRYPTED" or b"Proc-Type: 4,ENCRYPTED" in data:
        raise ConfigError(f"{setting} {path}: the private key is encrypted; gRPC needs it unencrypted")
    if found.group(1) == b"OPENSSH":
        raise ConfigError(f"{setting} {path}: an OpenSSH key, not a PEM (PKCS#1/PKCS#8) private key")
    try:
        from cryptography.exceptions import UnsupportedAlgorithm
        from cryptography.hazmat.primitives.serialization import load_pem_private_key
    except ImportError:
        return data, None
    try:
        return data, load_pem_private_key(data, password=None)
    except (ValueError, TypeError, UnsupportedAlgorithm):  # never the library's text: it may quote the file
        raise ConfigError(f"{setting} {path}: not a valid PEM private key") from None


def _public_der(key: Any) -> bytes:
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    return key.public_bytes(Encoding.DER, PublicFormat.SubjectPublicKeyInfo)


def _server_credentials(auth: AuthConfig) -> grpc.ServerCredentials | None:
    """TLS credentials from auth.tls_*, each file checked first so a bad one is named (gRPC would only
    fail the bind, which reads like a port problem)."""
    if not auth.tls_cert:
        for setting, value in (("auth.tls_key", auth.tls_key), ("auth.tls_client_ca", auth.tls_client_ca)):
            if value:  # silently serving plaintext (or without mTLS) would be worse than refusing to start
                raise ConfigError(f"{setting} is set but auth.tls_cert is not: a server needs both for TLS")
        return None
    if not auth.tls_key:
        raise ConfigError("auth.tls_key is required with auth.tls_cert")
    cert, certs = _pem_certificates("auth.tls_cert", auth.tls_cert)
    key, private = _pem_private_key("auth.tls_key", auth.tls_key)
    if certs and private is not None and _public_der(certs[0].public_key()) != _public_der(private.public_key()):
        raise ConfigError(f"auth.tls_key {auth.tls_key} does not match auth.tls_cert {auth.tls_cert}")
    if auth.tls_client_ca:  # mTLS: only clients with a certificate from this CA get a connection
        client_ca, _ = _pem_certificates("auth.tls_client_ca", auth.tls_client_ca)
        return grpc.ssl_server_credentials([(key, cert)], root_certificates=client_ca, require_client_auth=True)
    return grpc.ssl_server_credentials([(key, cert)])


def _bind_error(host_setting: str, port_setting: str, host: str, port: int) -> str | None:
    """Why host:port cannot be bound, naming the setting to change; None when it can.

    Found by binding a probe socket the way gRPC does (SO_REUSEADDR; every resolved address, and like
    gRPC, one that binds is enough): gRPC itself says only "Failed to bind" after logging the cause."""
    try:
        infos = socket.getaddrinfo(host.strip("[]") or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError):
        return f"{host_setting} {host!r} is not a known host name or address"
    errors: list[OSError] = []
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(addr)
                return None
            except OSError as exc:
                errors.append(exc)
    if not errors:
        return f"{host_setting} {host!r} resolves to no address"
    exc = errors[0]
    if exc.errno == errno.EADDRINUSE:
        return f"{port_setting} {port} is in use on {host}"
    if exc.errno == errno.EACCES:
        hint = " (ports below 1024 need root)" if 0 < port < 1024 else ""
        return f"{port_setting} {port} on {host}: permission denied{hint}"
    if exc.errno == errno.EADDRNOTAVAIL:
        return f"{host_setting} {host!r} is not an address of this machine"
    return f"{port_setting} {port} on {host}: {exc.strerror or exc}"


def start_server(
    name: str,
    register: Callable[[grpc.Server], None],
    service_names: Iterable[str],
    server_cfg: ServerConfig,
    auth: AuthConfig,
    start_metrics: bool = True,
) -> RunningServer:
    """Start a gRPC server with auth, metrics, health and reflection, plus /metrics over HTTP.

    `service_names` are the full names (e.g. user_pb2.DESCRIPTOR.services_by_name[...].full_name)
    reported SERVING by the health service and listed by reflection.
    """
    interceptors: list[grpc.ServerInterceptor] = [MetricsInterceptor()]
    table = auth_table(auth)
    token = table is not None
    if table is not None:
        interceptors.append(TokenAuthInterceptor(table))
    # after auth: a caller without a valid token is told so, not that the server is full
    interceptors.append(StreamLimitInterceptor(server_cfg.max_workers, f"{name}.server.max_workers"))
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=server_cfg.max_workers, thread_name_prefix=name),
        interceptors=interceptors,
        options=SERVER_OPTIONS,
    )
    register(server)
    names = list(service_names)
    health_servicer = health.HealthServicer(experimental_non_blocking=True)
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection([*names, health.SERVICE_NAME, reflection.SERVICE_NAME], server)
    host, bind = server_cfg.host, f"{server_cfg.host}:{server_cfg.port}"
    creds = _server_credentials(auth)
    settings = (f"{name}.server.host", f"{name}.server.port")
    # Probe first: a busy port then fails with our line alone, not after a C-core error log line too.
    why = _bind_error(*settings, host, server_cfg.port)
    if why is not None:
        raise ConfigError(why)
    metrics_http, metrics_port = None, 0
    if start_metrics:  # before gRPC binds: an unstarted gRPC server does not let go of its port on stop()
        metrics_http, metrics_port = start_metrics_http(
            host, server_cfg.metrics_port, f"{name}.server.host", f"{name}.server.metrics_port"
        )
    try:
        port = server.add_secure_port(bind, creds) if creds else server.add_insecure_port(bind)
    except RuntimeError:  # grpcio >= 1.60 raises; older versions return 0
        port = 0
    if port == 0:  # taken since the probe, or (the port being free) gRPC refused the certificate or key
        if metrics_http is not None:
            metrics_http.shutdown()
            metrics_http.server_close()
        why = _bind_error(*settings, host, server_cfg.port)
        if why is None and creds:
            why = f"{name}: gRPC could not serve TLS with auth.tls_cert {auth.tls_cert} and auth.tls_key {auth.tls_key}"
        raise ConfigError(why or f"{name}: cannot bind {bind}")
    server.start()
    for svc in [*names, ""]:
        health_servicer.set(svc, health_pb2.HealthCheckResponse.SERVING)
    log.info(
        "serving",
        extra={"fields": {"grpc_port": port, "metrics_port": metrics_port, "tls": bool(creds), "auth": bool(token)}},
    )
    return RunningServer(name, server, port, metrics_port, health_servicer, names, server_cfg.grace_s, metrics_http)


def start_metrics_http(
    host: str, port: int, host_setting: str = "metrics host", port_setting: str = "metrics port"
) -> tuple[Any, int]:
    """Serve /metrics on host:port; a port in use (or a bad host) is a ConfigError naming the setting."""
    try:
        httpd, _thread = prometheus_client.start_http_server(port, addr=host)
    except OSError as exc:
        why = _bind_error(host_setting, port_setting, host, port)
        raise ConfigError(why or f"{port_setting} {port} on {host}: {exc.strerror or exc}") from None
    return httpd, httpd.server_port


def remove_series(family: Any, label: str, value: str) -> None:
    """Remove every series of a labelled metric family whose `label` is `value` (an experiment removed, a robot
    forgotten): frozen values must not outlive what they measured."""
    names = family._labelnames  # prometheus_client keeps no public accessor for them
    keys = {
        tuple(s.labels[n] for n in names) for m in family.collect() for s in m.samples if s.labels.get(label) == value
    }
    for key in keys:
        family.remove(*key)


def install_signal_handlers() -> threading.Event:
    """SIGTERM and SIGINT set the returned event instead of killing the process."""
    stop = threading.Event()

    def handle(signum: int, _frame: Any) -> None:
        log.info("signal received, shutting down", extra={"fields": {"signal": signal.Signals(signum).name}})
        stop.set()

    signal.signal(signal.SIGTERM, handle)
    signal.signal(signal.SIGINT, handle)
    return stop


def write_ready_file(path: str | Path | None, **info: Any) -> None:
    """Atomically publish the bound ports so a supervisor (userctl up, tests) can find us."""
    if not path:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps({"pid": os.getpid(), **info}))
    os.replace(tmp, path)


class GrpcService(ABC):
    """What every USER service object is: start() serves (returns self), stop() shuts down gracefully
    and is safe to call twice; `running` is set while it serves."""

    running: RunningServer | None = None

    @abstractmethod
    def start(self) -> Any: ...

    @abstractmethod
    def stop(self) -> None: ...

    @property
    def port(self) -> int:
        assert self.running is not None, "not started"
        return self.running.port

    @property
    def address(self) -> str:
        assert self.running is not None, "not started"
        return self.running.address()


def serve_until_signal(
    service: GrpcService, name: str, ready_file: str | None, healthy: Callable[[], bool] = lambda: True
) -> bool:
    """The body of `userctl <service>`: start, publish the ports, serve until SIGTERM/Ctrl-C (or until
    healthy() turns false), stop gracefully. Returns whether it stopped healthy."""
    service.start()
    assert service.running is not None
    write_ready_file(ready_file, grpc_port=service.running.port, metrics_port=service.running.metrics_port)
    stop = install_signal_handlers()
    while not stop.wait(0.5) and healthy():
        pass
    ok = healthy()
    service.stop()
    log.info(f"{name} stopped")
    return ok


# --------------------------------------------------------------------------- client side


class _CallDetails(grpc.ClientCallDetails):
    def __init__(self, base: grpc.ClientCallDetails, metadata: list[tuple[str, str]]) -> None:
        self.method = base.method
        self.timeout = base.timeout
        self.metadata = metadata
        self.credentials = base.credentials
        self.wait_for_ready = base.wait_for_ready
        self.compression = base.compression


class TokenClientInterceptor(
    grpc.UnaryUnaryClientInterceptor,
    grpc.UnaryStreamClientInterceptor,
    grpc.StreamUnaryClientInterceptor,
    grpc.StreamStreamClientInterceptor,
):
    def __init__(self, token: str | Callable[[], str]) -> None:
        self._token = token if callable(token) else (lambda: token)

    def _details(self, details: grpc.ClientCallDetails) -> grpc.ClientCallDetails:
        return _CallDetails(details, [*(details.metadata or []), (AUTH_HEADER, f"Bearer {self._token()}")])

    def intercept_unary_unary(self, continuation, client_call_details, request):
        return continuation(self._details(client_call_details), request)

    def intercept_unary_stream(self, continuation, client_call_details, request):
        return continuation(self._details(client_call_details), request)

    def intercept_stream_unary(self, continuation, client_call_details, request_iterator):
        return continuation(self._details(client_call_details), request_iterator)

    def intercept_stream_stream(self, continuation, client_call_details, request_iterator):
        return continuation(self._details(client_call_details), request_iterator)


def make_channel(target: str, auth: AuthConfig) -> grpc.Channel:
    """A channel that sends the token on every call; TLS when auth.tls_ca is set."""
    if auth.tls_ca:  # an unreadable file is a ConfigError naming its field, like the server's
        key = _read_file("auth.tls_client_key", auth.tls_client_key) if auth.tls_client_key else None
        cert = _read_file("auth.tls_client_cert", auth.tls_client_cert) if auth.tls_client_cert else None
        creds = grpc.ssl_channel_credentials(
            root_certificates=_read_file("auth.tls_ca", auth.tls_ca), private_key=key, certificate_chain=cert
        )
        channel = grpc.secure_channel(target, creds, options=CHANNEL_OPTIONS)
    else:
        channel = grpc.insecure_channel(target, options=CHANNEL_OPTIONS)
    token = auth.resolved_token()
    if token:
        rotating = not auth.token and not os.environ.get("USER_TOKEN") and auth.token_file
        provider = FileToken(auth.token_file, token) if rotating else token
        channel = grpc.intercept_channel(channel, TokenClientInterceptor(provider))
    return channel


class FileToken:
    """A token read from a file and re-read when the file changes: rotation without restarting clients."""

    def __init__(self, path: Path, initial: str) -> None:
        self.path, self._token, self._checked, self._stamp = path, initial, 0.0, None
        self._lock = threading.Lock()

    def __call__(self) -> str:
        now = time.monotonic()
        if now - self._checked >= 1.0:
            with self._lock:
                self._checked = now
                try:
                    st = os.stat(self.path)
                    stamp = (st.st_mtime_ns, st.st_size, st.st_ino)
                    if stamp != self._stamp:
                        self._token = self.path.read_text().strip() or self._token
                        self._stamp = stamp
                except OSError:
                    pass  # keep the last token; the server will say UNAUTHENTICATED if it is stale
        return self._token


def check_health(target: str, auth: AuthConfig, service: str = "", timeout_s: float = 2.0) -> bool:
    """True when the server at `target` reports SERVING (used by docker health checks)."""
    with make_channel(target, auth) as channel:
        try:
            resp = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=service), timeout=timeout_s
            )
        except grpc.RpcError:
            return False
        return resp.status == health_pb2.HealthCheckResponse.SERVING


class Backoff:
    """Exponential backoff with full jitter for reconnect loops."""

    def __init__(self, initial_s: float = 0.1, max_s: float = 5.0, factor: float = 2.0) -> None:
        self.initial_s, self.max_s, self.factor = initial_s, max_s, factor
        self._next = initial_s

    def reset(self) -> None:
        self._next = self.initial_s

    def next_delay(self) -> float:
        delay = random.uniform(self.initial_s / 2, self._next)
        self._next = min(self._next * self.factor, self.max_s)
        return delay

    def sleep(self, stop: threading.Event | None = None) -> bool:
        """Sleep the next delay; returns False if `stop` was set meanwhile."""
        delay = self.next_delay()
        if stop is None:
            time.sleep(delay)
            return True
        return not stop.wait(delay)


def is_retryable(err: grpc.RpcError) -> bool:
    code = err.code() if hasattr(err, "code") else None
    return code in (
        grpc.StatusCode.UNAVAILABLE,
        grpc.StatusCode.DEADLINE_EXCEEDED,
        grpc.StatusCode.RESOURCE_EXHAUSTED,
        grpc.StatusCode.ABORTED,
        grpc.StatusCode.CANCELLED,
        grpc.StatusCode.INTERNAL,
        grpc.StatusCode.UNKNOWN,
    )
