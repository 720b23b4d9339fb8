"""Typed configuration: one YAML file describes a stack, each service reads its section.

Precedence: YAML file < environment (USER__SECTION__FIELD=value) < CLI (--set section.field=value).
Values from env/CLI are parsed as YAML scalars, so `--set learner.batch_size=128` is an int.
A bad config fails fast with the dotted path of the offending field.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from user.auth import is_placeholder

# torch device names; whether the machine has the device is checked when the service starts.
DEVICE = Field(default="cpu", pattern=r"^(cpu|cuda(:[0-9]+)?|mps)$", description="torch device: cpu, cuda, cuda:N")


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class AuthConfig(Strict):
    enabled: bool = Field(default=True, description="require `authorization: Bearer <token>` on every call")
    token: str | None = Field(
        default=None,
        description="shared (admin) token; default from $USER_TOKEN. Any length, unlike tokens_file entries "
        "(16+): use 16+ random characters",
    )
    token_file: Path | None = Field(default=None, description="file holding the token (docker/k8s secrets)")
    tls_cert: Path | None = Field(default=None, description="server cert (PEM); enables TLS")
    tls_key: Path | None = Field(default=None, description="server private key (PEM)")
    tls_ca: Path | None = Field(default=None, description="CA bundle clients trust; enables TLS")
    tokens_file: Path | None = Field(
        default=None, description="server: role tokens (admin/operator/reader/edge/worker), re-read on change"
    )
    tls_client_ca: Path | None = Field(default=None, description="server: require client certs from this CA (mTLS)")
    tls_client_cert: Path | None = Field(default=None, description="client certificate (PEM) for mTLS")
    tls_client_key: Path | None = Field(default=None, description="client private key (PEM) for mTLS")

    def resolved_token(self) -> str | None:
        if not self.enabled:
            return None
        if self.token or os.environ.get("USER_TOKEN"):
            setting, token = "auth.token ($USER_TOKEN)", self.token or os.environ["USER_TOKEN"]
        elif self.token_file:
            setting, token = "auth.token_file", read_token_file(self.token_file)
        else:
            raise ConfigError(
                "auth.token: auth is enabled but no token is set (auth.token, $USER_TOKEN or auth.token_file)"
            )
        if is_placeholder(token):  # the shipped examples' marker: servers refuse it too (user/auth.py)
            raise ConfigError(f"{setting}: the token is an example placeholder (REPLACE-ME); set a real secret")
        return token


def read_token_file(path: Path) -> str:
    """The token in auth.token_file; a ConfigError naming the setting and why (never the content): a traceback
    here would only say FileNotFoundError, and a service restarted on failure would loop on it."""
    try:
        token = path.read_text().strip()
    except OSError as exc:
        raise ConfigError(f"auth.token_file {path}: cannot read it ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"auth.token_file {path}: not UTF-8 text") from None
    if not token:
        raise ConfigError(f"auth.token_file {path}: the file is empty")
    return token


class ServerConfig(Strict):
    host: str = Field(default="127.0.0.1", description="bind address; 0.0.0.0 to serve other machines")
    port: int = Field(default=0, ge=0, le=65535, description="gRPC port; 0 = ephemeral")
    metrics_port: int = Field(default=0, ge=0, le=65535, description="Prometheus port; 0 = ephemeral")
    max_workers: int = Field(
        default=64, ge=1, description="gRPC handler threads; streams may hold all but a quarter (at least 4)"
    )
    grace_s: float = Field(default=5.0, ge=0, description="on SIGTERM, seconds in-flight calls get to finish")


class _ServerSection(Strict):
    """A section with a `server`: a partial server mapping keeps the section's own defaults for the rest
    (`--set control.server.host=0.0.0.0` must not reset control's port 50051 to the generic 0)."""

    @model_validator(mode="before")
    @classmethod
    def _fill_server_defaults(cls, data: Any) -> Any:
        if isinstance(data, dict) and isinstance(data.get("server"), dict):
            default = cls.model_fields["server"].default.model_dump()
            data = {**data, "server": {**default, **data["server"]}}
        return data


class ReplayShard(Strict):
    """One replay process and the edges that write to it (traffic stays in the site)."""

    addr: str = Field(description="replay address the matching edges write to")
    sites: list[str] = Field(default=[], description="edge.site labels served by this shard")
    agents: list[str] = Field(default=[], description="agent id patterns (fnmatch, e.g. lab-a-*)")


class ControlConfig(_ServerSection):
    server: ServerConfig = ServerConfig(port=50051, metrics_port=9101)
    lease_ttl_s: float = Field(default=10.0, gt=0, description="a robot without a heartbeat this long goes offline")
    heartbeat_interval_s: float = Field(default=1.0, gt=0, description="heartbeat period asked of edge agents")
    episodes_kept: int = Field(default=200, ge=1, description="recent episodes kept per robot")
    replay_shards: list[ReplayShard] = Field(
        default=[], description="replay shard per site/agent, first match wins; none: each edge its own replay_addr"
    )
    state_path: Path | None = Field(
        default=None, description="SQLite file for robots, episode history and workers; none = memory only"
    )
    worker_ttl_s: float = Field(default=30.0, gt=0, description="a worker not re-registering this long is offline")
    forget_offline_after_days: float = Field(
        default=0.0,
        ge=0,
        allow_inf_nan=False,
        description="a robot offline this long is forgotten (as userctl robots forget); 0 = never",
    )


class ReplayConfig(_ServerSection):
    server: ServerConfig = ServerConfig(port=50052, metrics_port=9102)
    path: Path = Field(default=Path("runs/default/replay"), description="LMDB directory (survives restarts)")
    map_size_mb: int = Field(default=4096, ge=16, description="LMDB map size: the most the buffer may hold")
    commit_max_steps: int = Field(default=256, ge=1, description="steps per LMDB transaction at most")
    commit_max_delay_ms: float = Field(default=20.0, ge=0, description="longest a received step waits for its commit")
    cache_mb: int = Field(default=256, ge=0, description="RAM hot tier: newest transitions as columns; 0 = off")
    control_addr: str = Field(default="127.0.0.1:50051", description="control service: robot specs to validate against")
    rpc_timeout_s: float = Field(default=5.0, gt=0, description="deadline on calls to control")
    max_map_mb: int = Field(default=0, ge=0, description="the LMDB map grows up to this; 0 = 4 x map_size_mb")
    capacity_mb: int = Field(
        default=0,
        ge=0,
        description="stored step bytes; beyond, the oldest ended episodes leave (none being written is cut); 0 = off",
    )
    durability: Literal["fsync", "os"] = Field(
        default="fsync", description="fsync: ack survives a power cut; os: survives kill -9, fsync every second"
    )
    prefetch_batches: int = Field(default=2, ge=0, description="batches assembled ahead per sample request kind")
    prefetch_max_age_ms: float = Field(default=50.0, ge=0, description="oldest prefetched batch served after inserts")
    min_size_to_sample: int = Field(default=0, ge=0, description="rate limiter: no samples below this many transitions")
    samples_per_insert: float = Field(default=0.0, ge=0, description="rate limiter: most sampled per inserted; 0 = off")
    samples_per_insert_slack: float = Field(
        default=10000.0, ge=0, description="rate limiter: sampled transitions of slack"
    )
    image_encoding: dict[str, Literal["raw", "jpeg", "png"]] = Field(
        default={}, description='camera frames in LMDB, e.g. {"*": "png", "camera.wrist": "jpeg"}; default raw'
    )
    decoded_mb: int = Field(
        default=0, ge=0, description="RAM for the newest JPEG/PNG camera frames kept decoded after a sample; 0 = off"
    )
    cache_prefault: bool = Field(
        default=True,
        description="touch the RAM tier's column pages when a layout first arrives, so RSS is at its plateau early",
    )
    attach: dict[str, Path] = Field(
        default={},
        description="read-only tables from other buffers, e.g. {prior: runs/old/replay} (not while their owner runs)",
    )
    shm_dir: str | None = Field(
        default="/dev/shm",
        description="same-host learners that prove they share this directory get batches as slot files here "
        "instead of through the socket; null = always through the socket",
    )
    shm_max_mb: int = Field(default=1024, ge=1, description="shared-memory slot files of all learners together")
    shm_slots: int = Field(
        default=8,
        ge=1,
        le=64,
        description="slot files per learner session: batches it may hold at once (its prefetch queue, one training)",
    )


class InferenceConfig(_ServerSection):
    server: ServerConfig = ServerConfig(port=50053, metrics_port=9103)
    learner_addr: str = Field(default="127.0.0.1:50054", description="learner whose weight stream is served")
    control_addr: str = Field(
        default="127.0.0.1:50051", description="control: which robot is in which experiment; registers this worker"
    )
    max_batch: int = Field(default=64, ge=1, description="most requests per policy forward")
    max_wait_ms: float = Field(default=2.0, ge=0, description="longest a request waits for others to batch with")
    batch_workers: int = Field(
        default=1, ge=1, description="batches in their forward at once per policy (CPU: up to the cores left over)"
    )
    continuous_batching: bool = Field(
        default=False,
        description="policies that sample in steps (flow_vla): requests join a running batch at its next step "
        "instead of waiting for it to end",
    )
    device: str = DEVICE
    matmul_precision: Literal["highest", "high"] = Field(
        default="highest",
        description="float32 matrix products: highest (true fp32) or high (TF32 on GPUs that have it; this process)",
    )
    weights_lossy: bool = Field(
        default=False,
        description="accept lossy weights (error-bounded patches, bf16) when lossless ones cannot stay fresh",
    )
    weights_shm_dir: str | None = Field(
        default="/dev/shm",
        description="same host: read weight versions from this shared-memory directory when the learner "
        "proves it is on this host and shares it; null = always over the stream",
    )


def _shortcut(what: str) -> str:
    return f"{what}; shortcut for the default experiment only (empty `experiments`)"


class LearnerConfig(_ServerSection):
    server: ServerConfig = ServerConfig(port=50054, metrics_port=9104)
    replay_addr: str = Field(default="127.0.0.1:50052", description="replay service to sample from")
    replay_addrs: list[str] = Field(
        default=[],
        description="replay shards sampled in proportion to their size (per table for table ratios); "
        "empty = replay_addr alone",
    )
    control_addr: str = Field(default="127.0.0.1:50051", description="control service: robot specs")
    checkpoint_dir: Path = Field(default=Path("runs/default/checkpoints"), description="resumes from the newest here")
    robot_kind: str = Field(
        default="sim_reach_arm", description="deprecated shortcut, used only when `experiments` is empty"
    )
    device: str = DEVICE
    torch_threads: int = Field(default=1, ge=1, description="intra-op threads for training")
    seed: int = 0
    # The implicit default experiment's SAC params (LEGACY_SAC_FIELDS): a changed one is refused with `experiments` set.
    hidden: list[int] = Field(default=[128, 128], description=_shortcut("MLP widths of actor and critics"))
    batch_size: int = Field(default=128, ge=1, description=_shortcut("transitions per update"))
    gamma: float = Field(default=0.95, gt=0, le=1, description=_shortcut("discount"))
    tau: float = Field(default=0.005, gt=0, le=1, description=_shortcut("Polyak rate of the target critics"))
    actor_lr: float = Field(default=1e-3, gt=0, description=_shortcut("actor learning rate"))
    critic_lr: float = Field(default=1e-3, gt=0, description=_shortcut("critic learning rate"))
    alpha_lr: float = Field(default=1e-3, gt=0, description=_shortcut("entropy temperature learning rate"))
    init_alpha: float = Field(default=0.1, gt=0, description=_shortcut("initial entropy temperature (then tuned)"))
    min_transitions: int = Field(default=250, ge=1, description="wait for this many before training")
    max_updates_per_transition: float = Field(
        default=4.0, gt=0, description="caps the update-to-data ratio so the learner cannot overfit a tiny buffer"
    )
    publish_every: int = Field(default=100, ge=1, description="updates between weight versions")
    checkpoint_every: int = Field(default=2000, ge=1, description="updates between checkpoints")
    prefetch_batches: int = Field(default=4, ge=1, description="batches sampled ahead while the learner trains")
    max_chunk_bytes: int = Field(default=1 << 20, ge=1024, description="weight stream chunk size cap")
    rpc_timeout_s: float = Field(default=10.0, gt=0, description="deadline on calls to replay and control")
    mode: Literal["async", "sync"] = Field(
        default="async", description="async: collect and train at once; sync: collect, pause robots, train, publish"
    )
    sync_env_steps: int = Field(default=200, ge=1, description="sync mode: new transitions per experiment per round")
    sync_updates: int = Field(default=200, ge=1, description="sync mode: updates per experiment per round")
    weights_freshness_s: float = Field(
        default=1.0, gt=0, description="weight streams pick per link the encoding that delivers a version within this"
    )
    weights_history: int = Field(default=4, ge=1, description="published versions kept as delta bases")
    replay_shm_dir: str | None = Field(
        default="/dev/shm",
        description="same host as replay: take batches from slot files replay writes in this shared-memory "
        "directory once it proves shared (not with replay_addrs shards); null = always through the socket",
    )
    replay_encoded_frames: bool = Field(
        default=True,
        description="batches through the socket bring camera frames as replay keeps them (JPEG/PNG, ~1/10 of raw) "
        "and the learner's sampler threads decode them; false = replay decodes",
    )
    weights_shm_dir: str | None = Field(
        default="/dev/shm",
        description="same-host subscribers that prove they share this directory get versions as files here "
        "(the newest 3 per experiment, 0600; payloads of 1 MiB and more are packed into mapped files here, so a "
        "version is a hard link, not a copy); null = every version over the stream",
    )


class RobotSelector(Strict):
    """Which robots an experiment trains on: every given criterion must hold (an empty one holds for all)."""

    kinds: list[str] = Field(default=[], description="robot kinds (RobotSpec.kind)")
    labels: dict[str, str] = Field(default={}, description="RobotSpec.labels that must all match")
    ids: list[str] = Field(default=[], description="robot ids")


class PluginChoice(Strict):
    kind: str = Field(min_length=1, description="a registered kind (`userctl plugins`)")
    params: dict[str, Any] = Field(default={}, description="the kind's typed params, checked at start")


TABLE_NAME = r"^[A-Za-z0-9_.\-]{1,64}$"  # replay's table-name pattern


class PretrainConfig(Strict):
    """Updates on a pre-filled replay table (e.g. imported demos) before the experiment's first weight version."""

    table: str = Field(default="demos", pattern=TABLE_NAME, description="replay table to pretrain on")
    steps: int = Field(ge=1, description="gradient updates before the first weight version is published")
    min_size: int = Field(default=1, ge=1, description="wait until the table holds this many transitions")
    human: bool = Field(
        default=True, description="every row is a demonstrated action: batches mark them intervention (BC terms)"
    )


class NormalizeConfig(Strict):
    """State normalization statistics computed by the learner from a replay table, shipped with the policy."""

    from_table: str = Field(
        default="demos", pattern=TABLE_NAME, description="table the statistics come from (the experiment's own: online)"
    )
    min_steps: int = Field(default=1000, ge=2, description="wait until the table holds this many transitions")
    samples: int = Field(default=8192, ge=2, description="transitions sampled (uniformly) for mean and std")
    keys: list[str] = Field(default=[], description="float state features to normalize; empty = every one")
    min_std: float = Field(default=1e-2, gt=0, description="std floor: a near-constant feature is not blown up")


class ExperimentConfig(Strict):
    """One learning problem: robots (selector), policy, algorithm, replay table. Several train at once."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="names checkpoints, weights and metrics")
    robots: RobotSelector = RobotSelector()
    policy: PluginChoice | None = Field(default=None, description="policy kind and params; None = the algorithm's")
    algorithm: PluginChoice = PluginChoice(kind="sac")
    table: str = Field(
        default="online", pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="replay table the experiment's robots fill"
    )
    shared_embodiment: bool = Field(
        default=False, description="one policy for robots of different shapes: pad state/action, mask, embodiment id"
    )
    max_robots: int = Field(
        default=0, ge=0, description="control leases at most this many of the selected robots; 0 = all of them"
    )
    pretrain: PretrainConfig | None = Field(
        default=None, description="train on a pre-filled table before the first weight version; robots hold till then"
    )
    normalize: NormalizeConfig | None = Field(
        default=None, description="learner computes state mean/std from a table; stored in checkpoints and the policy"
    )

    @model_validator(mode="after")
    def _prepare_fits(self) -> ExperimentConfig:
        if self.shared_embodiment and (self.normalize is not None or self.pretrain is not None):
            raise ValueError(
                "normalize / pretrain: not supported with shared_embodiment yet (padded state and actions)"
            )
        if self.pretrain is not None and self.normalize is not None and self.normalize.from_table == self.table:
            raise ValueError(
                f"normalize.from_table: {self.table!r} is the table the robots fill, but pretraining runs before they "
                f"act; take the statistics from a pre-filled table (e.g. pretrain.table {self.pretrain.table!r})"
            )
        return self


# SAC fields of the learner section that the implicit default experiment (learner.robot_kind) passes on.
LEGACY_SAC_FIELDS = ("hidden", "batch_size", "gamma", "tau", "actor_lr", "critic_lr", "alpha_lr", "init_alpha")


class PluginConfig(Strict):
    """One plug-in choice: a registered kind and its params (validated against the kind's Params at start)."""

    kind: str = Field(min_length=1, description="registered kind")
    params: dict[str, Any] = Field(default={}, description="the kind's typed params")


HARDWARE_ROBOT_KINDS = ("lerobot",)  # robot kinds that drive physical devices (no simulator to step faster)


class RobotConfig(Strict):
    id: str = Field(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")
    kind: str = Field(default="sim_reach_arm", description="registered robot kind")
    params: dict[str, Any] = Field(default={}, description="keyword arguments of the robot class")
    task: PluginConfig | None = Field(
        default=None, description="reward/success judge {kind, params}; none: the robot's default (reach, env)"
    )
    teleop: PluginConfig | None = Field(
        default=None, description="who may take over {kind, params}, e.g. scripted_expert; none: the policy drives"
    )
    image_encoding: dict[str, Literal["raw", "jpeg", "png"]] = Field(
        default={},
        description='camera frames encoded on the edge before the spool, e.g. {"*": "jpeg"} (* = every camera.*); '
        "default raw",
    )
    jpeg_quality: int = Field(default=90, ge=1, le=100, description="JPEG quality of image_encoding jpeg (1-100)")
    act_image_encoding: dict[str, Literal["raw", "jpeg", "png"]] | None = Field(
        default=None,
        description="camera frames of Act requests to a remote inference service, same form as image_encoding; "
        "null = as image_encoding (the policy sees frames as the learner does), {} = raw",
    )


class EdgeConfig(Strict):
    agent_id: str = Field(default="edge-0", description="this robot PC's name at the control service")
    control_addr: str = "127.0.0.1:50051"
    replay_addr: str = "127.0.0.1:50052"
    inference_addr: str = Field(default="127.0.0.1:50053", description="used when policy_source=remote")
    learner_addr: str = Field(default="127.0.0.1:50054", description="weight stream, used when policy_source=local")
    metrics_port: int = Field(default=9105, ge=0, le=65535, description="Prometheus port; 0 = ephemeral")
    metrics_host: str = "127.0.0.1"
    policy_source: Literal["remote", "local"] = Field(
        default="remote", description="remote: ask the inference service; local: run a weight-streamed copy"
    )
    mode: Literal["realtime", "fast"] = Field(
        default="realtime", description="realtime: each robot's spec.control_rate_hz; fast: unthrottled"
    )
    action_deadline_ms: float = Field(default=40.0, gt=0, description="no action by then -> hold still")
    seed: int = 0
    robots: list[RobotConfig] = Field(default=[RobotConfig(id="arm-0")], description="robots this agent drives")
    max_unacked_steps: int = Field(
        default=100_000, ge=1, description="spool_dir null: steps kept in RAM for re-send; the oldest drop beyond"
    )
    rpc_timeout_s: float = Field(default=5.0, gt=0, description="deadline on unary calls")
    site: str = Field(default="", description="where this robot PC stands; control maps it to a replay shard")
    spool_dir: Path | None = Field(
        default=Path("runs/default/spool"),
        description="LMDB outbox (a subdir per agent_id): steps stay until replay acks them; null = RAM only",
    )
    spool_max_mb: int = Field(default=1024, ge=1, description="spool byte cap (step bytes)")
    spool_full_policy: Literal["pause", "drop_oldest"] = Field(
        default="pause", description="at the cap: pause collection (robots hold) or drop the oldest steps"
    )
    encode_threads: int = Field(
        default=2, ge=1, le=64, description="threads encoding camera frames (robots with image_encoding), off the loops"
    )
    spool_fsync: bool = Field(
        default=False, description="fsync every spooled step (survives power loss); off: synced each second"
    )
    weights_lossy: bool = Field(
        default=False,
        description="local policy: accept lossy weights (error-bounded patches, bf16) when the link is too slow",
    )
    weights_shm_dir: str | None = Field(
        default="/dev/shm",
        description="local policy, same host: read weight versions from this shared-memory directory when the learner "
        "proves it is on this host and shares it; null = always over the stream",
    )
    replug_s: float = Field(
        default=2.0,
        ge=0,
        description="hot-plug: retry a robot absent at start or unplugged (its loop failed) after this many seconds, "
        "doubling per failed try up to 60 s; it registers when it connects. 0 = off: a robot that does not connect "
        "stops the agent",
    )

    @model_validator(mode="after")
    def _unique_ids(self) -> EdgeConfig:
        ids = [r.id for r in self.robots]
        if len(ids) != len(set(ids)):
            raise ValueError(f"robot ids must be unique, got {ids}")
        return self

    @model_validator(mode="after")
    def _fast_only_for_sims(self) -> EdgeConfig:
        # fast steps as quickly as the loop turns: a physical robot would be commanded far above its control rate
        if self.mode == "fast" and (real := [r.id for r in self.robots if r.kind in HARDWARE_ROBOT_KINDS]):
            raise ValueError(
                f"edge.mode: fast (unthrottled) is for simulated robots; {real} drive hardware "
                f"(kind {'/'.join(HARDWARE_ROBOT_KINDS)}): use realtime"
            )
        return self


class UpConfig(Strict):
    name: str = Field(default="demo", pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="data goes to runs_dir/name")
    runs_dir: Path = Path("runs")
    budget_s: float = Field(default=600.0, gt=0, description="stop after this many seconds")
    target_success: float = Field(default=0.9, gt=0, le=1, description="stop at this success rate")
    window_episodes: int = Field(
        default=20, ge=1, description="over the last this many episodes of the target experiment's robots"
    )
    edge_agents: int = Field(
        default=2, ge=1, description="processes driving copies of the first edge.robots entry; others run once each"
    )
    console: bool = Field(default=True, description="live table; false prints only the summary")
    target_experiment: str = Field(
        default="", description="the experiment (of `experiments`) whose success stops the run; empty = the first"
    )
    max_restarts: int = Field(
        default=3,
        ge=0,
        description="a child that dies mid-run starts again on its ports (learner and replay resume from their "
        "checkpoint and LMDB) up to this many times each; 0 = the run stops",
    )
    log_max_mb: float = Field(
        default=64.0,
        ge=0,
        description="a child's log in runs_dir/name/logs past this size is copied to <log>.1 (replacing it) and "
        "emptied, so a run of days keeps at most twice this per child; 0 = never",
    )


class StackConfig(Strict):
    auth: AuthConfig = AuthConfig()
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    log_json: bool = Field(default=True, description="one JSON object per log line; false for plain text")
    control: ControlConfig = ControlConfig()
    replay: ReplayConfig = ReplayConfig()
    inference: InferenceConfig = InferenceConfig()
    learner: LearnerConfig = LearnerConfig()
    edge: EdgeConfig = EdgeConfig()
    up: UpConfig = UpConfig()
    experiments: list[ExperimentConfig] = Field(
        default=[], description="what the learner trains; empty = one `default` sac experiment on learner.robot_kind"
    )

    @model_validator(mode="after")
    def _experiment_names_unique(self) -> StackConfig:
        names = [e.name for e in self.experiments]
        if len(names) != len(set(names)):
            raise ValueError(f"experiments: names must be unique, got {names}")
        return self

    @model_validator(mode="after")
    def _no_ignored_learner_params(self) -> StackConfig:
        """The learner's SAC fields only reach the implicit default experiment: with `experiments` set a
        changed one would be silently ignored, so it is refused, pointing at where it takes effect."""
        if not self.experiments:
            return self
        defaults = LearnerConfig.model_fields
        for name in LEGACY_SAC_FIELDS:
            if getattr(self.learner, name) != defaults[name].default:
                raise ValueError(
                    f"learner.{name}: ignored because `experiments` is set; set "
                    f"experiments[i].algorithm.params.{name} instead"
                )
        return self

    @model_validator(mode="after")
    def _target_experiment_known(self) -> StackConfig:
        # A typo would not stop the run at its target: it would run the whole budget and report no success.
        names = [e.name for e in self.resolved_experiments()]
        if self.up.target_experiment and self.up.target_experiment not in names:
            raise ValueError(
                f"up.target_experiment: {self.up.target_experiment!r} is not an experiment of this config; "
                f"known: {', '.join(names)}"
            )
        return self

    def resolved_experiments(self) -> list[ExperimentConfig]:
        """The configured experiments, or the deprecated shortcut: one sac experiment on learner.robot_kind
        with the learner section's SAC fields as its params."""
        if self.experiments:
            return list(self.experiments)
        params = {k: getattr(self.learner, k) for k in LEGACY_SAC_FIELDS}
        return [
            ExperimentConfig(
                name="default",
                robots=RobotSelector(kinds=[self.learner.robot_kind]),
                algorithm=PluginChoice(kind="sac", params=params),
            )
        ]


class ConfigError(ValueError):
    """Raised with a message naming the offending field."""


def _set_path(tree: dict[str, Any], dotted: str, value: Any) -> None:
    keys = dotted.split(".")
    node = tree
    for key in keys[:-1]:
        nxt = node.get(key)
        if not isinstance(nxt, dict):
            nxt = {}
            node[key] = nxt
        node = nxt
    node[keys[-1]] = value


def _env_overrides(environ: dict[str, str]) -> list[tuple[str, Any]]:
    out = []
    for key, raw in environ.items():
        if key.startswith("USER__"):
            dotted = ".".join(part.lower() for part in key[len("USER__") :].split("__"))
            out.append((dotted, yaml.safe_load(raw)))
    return out


def load_config(
    path: str | Path | None = None,
    overrides: list[str] | None = None,
    environ: dict[str, str] | None = None,
) -> StackConfig:
    tree: dict[str, Any] = {}
    if path is not None:
        try:
            loaded = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config {path}: {exc}") from exc
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"{path}: top level must be a mapping")
        tree = loaded or {}
    for dotted, value in _env_overrides(dict(os.environ if environ is None else environ)):
        _set_path(tree, dotted, value)
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.field=value")
        dotted, raw = item.split("=", 1)
        _set_path(tree, dotted.strip(), yaml.safe_load(raw))
    try:
        return StackConfig.model_validate(tree)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            if not err["loc"] and err["type"] == "value_error":  # a cross-field check names its field itself
                lines.append(str(err["ctx"]["error"]))
                continue
            where = ".".join(str(p) for p in err["loc"]) or "<root>"
            lines.append(f"{where}: {err['msg']}")
        raise ConfigError("invalid config: " + "; ".join(lines)) from None


def reference_markdown(instance: BaseModel | None = None, prefix: str = "") -> list[str]:
    """One table row per leaf field with its default: the README's config reference comes from here."""
    instance = instance if instance is not None else StackConfig()
    rows: list[str] = []
    for name, info in type(instance).model_fields.items():
        path, value = f"{prefix}{name}", getattr(instance, name)
        if isinstance(value, BaseModel):
            rows += reference_markdown(value, f"{path}.")
            continue
        if isinstance(value, list) and value and isinstance(value[0], BaseModel):
            value = [v.model_dump(mode="json") for v in value]
        elif isinstance(value, Path):
            value = str(value)
        text = (info.description or "").replace("|", "/")
        rows.append(f"| `{path}` | `{value}` | {text} |")
    return rows
