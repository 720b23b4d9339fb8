"""Who may call what: role tokens (or mTLS certificate names), checked per method by user/rpc.py.

Roles:
  admin     every method. The single `auth.token` is an admin token (services use it between themselves),
            so a stack configured with one shared token works as before.
  operator  reads everything and calls every write method except the edge's own (Connect, Insert) and the
            workers' (RegisterWorker): commands, experiments.
  reader    read-only methods (List*, Get*, Stats, Status, Sample with Replay.OpenSharedMemory, SubscribeWeights
            and StreamWeights) for dashboards and tools.
  edge      what an edge agent needs: Control.Connect (as its own agent_id, only its robots), Replay.Insert
            and InsertBatch (steps of its robots), Inference.Act and ActBatch, Learner.SubscribeWeights and
            StreamWeights (a local policy's weights). Nothing else: it cannot read the fleet.
  worker    Control.RegisterWorker (learner and inference hosts reporting their devices) plus reads.

The tokens file (auth.tokens_file) is a YAML list, re-read when it changes, so tokens rotate without
restarting anything: add the new token, move clients to it, remove the old one. A token containing REPLACE-ME
(the marker of the shipped examples) is refused, naming the setting.

    - {token: "s3cret-operator-alice", role: operator, name: alice}    # tokens: 16+ characters
    - {token: "s3cret-dashboard-grafana", role: reader, name: grafana}
    - {token: "s3cret-edge-lab-pc-1", role: edge, agent_id: lab-pc-1, robots: ["so100-*"]}
    - {cert_cn: "lab-pc-2", role: edge, agent_id: lab-pc-2}     # identified by its mTLS client certificate
"""

from __future__ import annotations

import fnmatch
import hmac
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

log = logging.getLogger(__name__)

Role = Literal["admin", "operator", "reader", "edge", "worker"]
READ_PREFIXES = ("List", "Get", "Stats", "Status", "Sample", "Subscribe")
# reads by another name: a shared-memory session only changes how Sample's batches travel (bounded per replay);
# StreamWeights is SubscribeWeights with acks on the same stream (what user.weights.WeightSubscriber calls)
READ_METHODS = frozenset({"/user.v1.Replay/OpenSharedMemory", "/user.v1.Learner/StreamWeights"})
EDGE_METHODS = frozenset(
    {
        "/user.v1.Control/Connect",
        "/user.v1.Replay/Insert",
        "/user.v1.Replay/InsertBatch",
        "/user.v1.Inference/Act",
        "/user.v1.Inference/ActBatch",
        "/user.v1.Learner/SubscribeWeights",
        "/user.v1.Learner/StreamWeights",
    }
)
EDGE_WRITES = frozenset({"/user.v1.Control/Connect", "/user.v1.Replay/Insert", "/user.v1.Replay/InsertBatch"})
WORKER_WRITES = frozenset({"/user.v1.Control/RegisterWorker"})
RELOAD_CHECK_S = 1.0  # how often the tokens file's mtime is looked at
# The shipped examples (deploy/k8s/components/tokens/*.example) carry this marker: such a token is public.
PLACEHOLDER = "replace-me"


def is_placeholder(token: str | None) -> bool:
    """True for an example token copied as is (contains REPLACE-ME, any case): never accepted."""
    return token is not None and PLACEHOLDER in token.lower()


class TokenEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    token: str | None = Field(default=None, min_length=16, description="bearer token (16+ characters)")
    cert_cn: str | None = Field(default=None, description="or: the common name of an mTLS client certificate")
    role: Role
    name: str = Field(default="", description="who holds it (logs)")
    agent_id: str | None = Field(default=None, description="edge: the only agent_id it may register")
    robots: list[str] = Field(default=["*"], description="edge: robot id patterns (fnmatch) it may register/write")


_ENTRIES = TypeAdapter(list[TokenEntry])


@dataclass(frozen=True)
class Identity:
    role: Role
    name: str = ""
    agent_id: str | None = None
    robots: tuple[str, ...] = ("*",)

    def may_call(self, method: str) -> bool:
        if self.role == "admin":
            return True
        if self.role == "edge":
            return method in EDGE_METHODS
        is_read = method.rsplit("/", 1)[-1].startswith(READ_PREFIXES) or method in READ_METHODS
        if self.role == "reader":
            return is_read
        if self.role == "worker":
            return is_read or method in WORKER_WRITES
        return method not in EDGE_WRITES and method not in WORKER_WRITES  # operator

    def owns_robot(self, robot_id: str) -> bool:
        """An edge identity writes only robots matching its patterns; other roles are not limited."""
        return self.role != "edge" or any(fnmatch.fnmatchcase(robot_id, p) for p in self.robots)

    def owns_agent(self, agent_id: str) -> bool:
        return self.role != "edge" or self.agent_id is None or self.agent_id == agent_id


ADMIN = Identity("admin", "shared-token")


class AuthError(ValueError):
    """A tokens file that cannot be used (names the file and the problem)."""


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """Where and what, without the excerpt of the offending line PyYAML adds (it would show a token)."""
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return f"not valid YAML: {where}{getattr(exc, 'problem', None) or 'cannot parse'}"


def _validation_problem(exc: ValidationError) -> str:
    """One line naming each bad entry and field. Only pydantic's messages, never the input: a token pasted
    into the wrong field would be printed and logged otherwise."""
    problems = []
    for err in exc.errors(include_url=False, include_context=False, include_input=False):
        loc = err["loc"]
        if not loc:
            problems.append(f"must be a YAML list of entries ({err['msg']})")
            continue
        field = ".".join(str(part) for part in loc[1:])
        problems.append(f"entry {loc[0]}{': ' + field if field else ''}: {err['msg']}")
    shown = "; ".join(problems[:3])
    return shown + (f"; and {len(problems) - 3} more" if len(problems) > 3 else "")


def load_entries(path: Path) -> list[TokenEntry]:
    """The entries of a tokens file; an AuthError names the file, the entry (index from 0) and the field,
    never a value."""
    try:
        raw = yaml.safe_load(path.read_text()) or []
    except OSError as exc:
        raise AuthError(f"auth.tokens_file {path}: cannot read it ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise AuthError(f"auth.tokens_file {path}: not UTF-8 text") from None
    except yaml.YAMLError as exc:
        raise AuthError(f"auth.tokens_file {path}: {_yaml_problem(exc)}") from None
    try:
        entries = _ENTRIES.validate_python(raw)
    except ValidationError as exc:
        raise AuthError(f"auth.tokens_file {path}: {_validation_problem(exc)}") from None
    for i, e in enumerate(entries):
        if (e.token is None) == (e.cert_cn is None):
            raise AuthError(f"auth.tokens_file {path}: entry {i}: needs exactly one of token or cert_cn")
        if e.role == "edge" and not e.agent_id:
            raise AuthError(f"auth.tokens_file {path}: entry {i}: an edge entry needs agent_id")
        if is_placeholder(e.token):
            raise AuthError(f"auth.tokens_file {path}: entry {i}: token is an example placeholder (REPLACE-ME)")
    return entries


@dataclass
class AuthTable:
    """Tokens and certificate names -> identities; re-reads its files when they change (rotation)."""

    shared_token: str | None = None
    token_file: Path | None = None  # the shared (admin) token, re-read too
    tokens_file: Path | None = None
    _tokens: list[tuple[bytes, Identity]] = field(default_factory=list)
    _certs: dict[str, Identity] = field(default_factory=dict)
    _stamp: tuple = ()
    _checked: float = 0.0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self._reload(force=True)

    def _file_stamp(self) -> tuple:
        stamp = []
        for path in (self.token_file, self.tokens_file):
            try:
                st = os.stat(path) if path else None
                stamp.append((st.st_mtime_ns, st.st_size, st.st_ino) if st else None)
            except OSError:
                stamp.append("missing")
        return tuple(stamp)

    def _read_shared(self, force: bool) -> str | None:
        """The shared (admin) token. AuthError naming the setting (never the value) for a placeholder, or for an
        unreadable token_file at start; later a vanished file only drops the token (as before)."""
        shared = self.shared_token
        if self.token_file and not shared:
            try:
                shared = self.token_file.read_text().strip() or None
            except OSError as exc:
                if force:
                    why = exc.strerror or exc
                    raise AuthError(f"auth.token_file {self.token_file}: cannot read it ({why})") from None
        if is_placeholder(shared):
            setting = "auth.token_file" if self.token_file and not self.shared_token else "auth.token ($USER_TOKEN)"
            raise AuthError(f"{setting}: the token is an example placeholder (REPLACE-ME); set a real secret")
        return shared

    def _reload(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._checked < RELOAD_CHECK_S:
            return
        with self._lock:
            self._checked = now
            stamp = self._file_stamp()
            if not force and stamp == self._stamp:
                return
            try:
                shared = self._read_shared(force)
                entries = load_entries(self.tokens_file) if self.tokens_file else []
            except AuthError as exc:
                if force:
                    raise
                log.error("tokens unusable; keeping the previous tokens", extra={"fields": {"error": str(exc)}})
                return
            tokens: list[tuple[bytes, Identity]] = [(shared.encode(), ADMIN)] if shared else []
            certs: dict[str, Identity] = {}
            for e in entries:
                ident = Identity(e.role, e.name or e.role, e.agent_id, tuple(e.robots))
                if e.token:
                    tokens.append((e.token.encode(), ident))
                else:
                    certs[e.cert_cn] = ident
            self._tokens, self._certs, self._stamp = tokens, certs, stamp
            if not force:
                log.info("auth tokens reloaded", extra={"fields": {"tokens": len(tokens), "certs": len(certs)}})

    @property
    def empty(self) -> bool:
        return not self._tokens and not self._certs

    def identify(self, bearer: str, cert_names: list[str]) -> Identity | None:
        """The identity of `authorization: Bearer <token>` or of a verified client certificate name."""
        self._reload()
        given = bearer.removeprefix("Bearer ").encode() if bearer.startswith("Bearer ") else b""
        found = None
        for token, ident in self._tokens:  # compare with every token: no early exit to time
            if hmac.compare_digest(given, token) and found is None:
                found = ident
        if found is None:
            for name in cert_names:
                if name in self._certs:
                    return self._certs[name]
        return found
