"""smolvla: lerobot 0.6.1's SmolVLA behind the Policy interface, from a local checkpoint folder.

A lerobot checkpoint folder (what `hf download lerobot/smolvla_base` leaves on disk, or what
`save_checkpoint` writes) holds config.json (SmolVLAConfig), model.safetensors and the
pre/post-processor pipelines; the config's `vlm_model_name` names the VLM backbone folder (its
config, tokenizer and processor). Nothing is downloaded at run time: both are paths.

- `load_checkpoint(folder)` is the one loading path, for a user's downloaded checkpoint and for
  the tiny ones tests build with `make_tiny_backbone` + `save_checkpoint`: lerobot's own
  `SmolVLAPolicy.from_pretrained` and `make_pre_post_processors(pretrained_path=...)`.
- On the wire it is like every policy: PolicySpec(kind="smolvla", config_json={"checkpoint":
  folder, feature mapping, action bounds}) + the module's named raw tensors. `build_policy`
  rebuilds the architecture from the folder's config and loads the streamed tensors (not the
  folder's weights), so learner updates reach inference and edges without pickle.

Checks: a folder that is not a loadable smolvla checkpoint (`check_folder`: another policy type, a missing
backbone folder, processor file or unreadable model.safetensors) or a spec that does not fit the model's config
(`check_spec`: action_dim, cameras, state keys) is a ValueError naming the file or field when the policy is
built; a request whose state keys do not hold the model's state size is refused by `check_observation`.

Observation mapping: camera features (uint8 H, W, 3) become `observation.images.<name>` floats in
[0, 1], state features are concatenated into `observation.state`, the instruction becomes the
`task` string lerobot's tokenizer step reads.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from user.policy import Policy, check_device, load_tensors, module_tensors, register_policy
from user.text import INSTRUCTION_KEY, decode_instruction
from user.v1 import learner_pb2

KIND = "smolvla"
CONFIG_FILE, WEIGHTS_FILE = "config.json", "model.safetensors"
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")  # lerobot's default pipeline names
IMAGES, STATE = "observation.images", "observation.state"
SPECIAL_TOKENS = {
    "fake_image_token": "<fake_token_around_image>",
    "image_token": "<image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
}


class SmolVlaSpec(BaseModel):
    """What the PolicySpec's config_json holds: where the architecture lives and how features map."""

    model_config = ConfigDict(extra="forbid")

    checkpoint: str = Field(description="local lerobot checkpoint folder (config.json, processors)")
    image_keys: dict[str, str] = Field(default_factory=dict, description="robot camera feature -> lerobot camera name")
    state_keys: list[str] = Field(default_factory=list)
    action_dim: int = Field(ge=1)
    action_low: list[float]
    action_high: list[float]
    default_instruction: str = ""

    @model_validator(mode="after")
    def _fits(self) -> SmolVlaSpec:
        for name, values in (("action_low", self.action_low), ("action_high", self.action_high)):
            if len(values) != self.action_dim:
                raise ValueError(f"{name} has {len(values)} values, action_dim is {self.action_dim}")
        # low == high is a fixed dimension (a robot's spec allows it); NaN fails the comparison
        if not all(low <= high for low, high in zip(self.action_low, self.action_high, strict=True)):
            raise ValueError("action_low must not exceed action_high (elementwise)")
        cameras = list(self.image_keys.values())
        if len(set(cameras)) != len(cameras):
            raise ValueError(f"image_keys maps two features to one camera: {self.image_keys}")
        return self


def policy_spec(spec: SmolVlaSpec) -> learner_pb2.PolicySpec:
    return learner_pb2.PolicySpec(kind=KIND, config_json=spec.model_dump_json())


# --- folders --------------------------------------------------------------------------------------


# Architectures a backbone folder can be built at (random weights). "smolvlm2_500m" is
# HuggingFaceTB/SmolVLM2-500M-Video-Instruct's shape (SmolLM2-360M text model, SigLIP-B/16 at 512 px,
# pixel shuffle 4), what lerobot/smolvla_base fine-tunes: for timing the real model where no hub is
# reachable. A user's downloaded folder is used as it is.
BACKBONES: dict[str, dict[str, Any]] = {
    "tiny": {
        "text": {
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "num_key_value_heads": 1,
            "head_dim": 16,
            "max_position_embeddings": 256,
        },
        "vision": {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1, "num_attention_heads": 2},
        "scale_factor": 2,
        "vocab_size": None,  # the word-level tokenizer's
    },
    "smolvlm2_500m": {
        "text": {
            "hidden_size": 960,
            "intermediate_size": 2560,
            "num_hidden_layers": 32,
            "num_attention_heads": 15,
            "num_key_value_heads": 5,
            "head_dim": 64,
            "max_position_embeddings": 8192,
            "rope_theta": 100000.0,
            "rms_norm_eps": 1e-5,
        },
        "vision": {"hidden_size": 768, "intermediate_size": 3072, "num_hidden_layers": 12, "num_attention_heads": 12},
        "scale_factor": 4,
        "vocab_size": 49280,
    },
}


def make_backbone(folder: str | Path, words: Sequence[str], image_size: int = 64, size: str = "tiny") -> Path:
    """A SmolVLM backbone folder (config, word-level tokenizer, processor) with a `BACKBONES` shape.

    Stands in for HuggingFaceTB/SmolVLM2-500M-Video-Instruct, which cannot be downloaded here; the
    real one is used by pointing the SmolVLA config's vlm_model_name at its local folder.
    """
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import Idefics3ImageProcessor, Idefics3Processor, PreTrainedTokenizerFast, SmolVLMConfig

    shape = BACKBONES[size]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tokens = ["<pad>", "<unk>", *SPECIAL_TOKENS.values(), *dict.fromkeys(w.lower() for w in words), "\n"]
    vocab = {t: i for i, t in enumerate(tokens)}
    vocab_size = shape["vocab_size"] or len(vocab)
    backend = Tokenizer(models.WordLevel(vocab=vocab, unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=backend, pad_token="<pad>", unk_token="<unk>", extra_special_tokens=SPECIAL_TOKENS
    )
    images = Idefics3ImageProcessor(
        do_resize=True,
        size={"longest_edge": image_size},
        max_image_size={"longest_edge": image_size},
        do_image_splitting=False,
    )
    seq_len = (image_size // 16 // shape["scale_factor"]) ** 2
    Idefics3Processor(image_processor=images, tokenizer=tokenizer, image_seq_len=max(seq_len, 1)).save_pretrained(
        folder
    )
    SmolVLMConfig(
        text_config={"model_type": "llama", "vocab_size": vocab_size, "pad_token_id": 0, **shape["text"]},
        vision_config={"model_type": "smolvlm_vision", "image_size": image_size, "patch_size": 16, **shape["vision"]},
        scale_factor=shape["scale_factor"],
        image_token_id=vocab["<image>"],
        vocab_size=vocab_size,
    ).save_pretrained(folder)
    return folder


def make_tiny_backbone(folder: str | Path, words: Sequence[str], image_size: int = 64) -> Path:
    """A SmolVLM backbone folder at test size (~100k parameters)."""
    return make_backbone(folder, words, image_size, "tiny")


def smolvla_base_config(backbone: str | Path, cameras: Sequence[str], state_dim: int, action_dim: int) -> Any:
    """lerobot's SmolVLAConfig at smolvla_base's sizes (16 VLM layers, chunks of 50 in 10 flow steps,
    512 px images) over `backbone` (a `make_backbone(..., size="smolvlm2_500m")` folder or a real one)."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    inputs = {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, 512, 512)) for c in cameras}
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (state_dim,))
    return SmolVLAConfig(
        vlm_model_name=str(backbone),
        load_vlm_weights=False,
        device="cpu",
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )


def tiny_smolvla_config(
    backbone: str | Path,
    cameras: Sequence[str],
    state_dim: int,
    action_dim: int,
    horizon: int = 8,
    image_size: int = 64,
) -> Any:
    """A SmolVLAConfig over a (tiny) backbone folder, with lerobot's feature names."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    inputs = {
        f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size)) for c in cameras
    }
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (state_dim,))
    return SmolVLAConfig(
        vlm_model_name=str(backbone),
        load_vlm_weights=False,
        chunk_size=horizon,
        n_action_steps=horizon,
        max_state_dim=max(state_dim, 1),
        max_action_dim=action_dim,
        resize_imgs_with_padding=(image_size, image_size),
        num_vlm_layers=2,
        num_steps=3,
        tokenizer_max_length=16,
        device="cpu",
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )


def save_checkpoint(model: Any, folder: str | Path, preprocessor: Any = None, postprocessor: Any = None) -> Path:
    """Write a lerobot checkpoint folder (config.json, model.safetensors, processor pipelines)."""
    from lerobot.policies.factory import make_pre_post_processors

    folder = Path(folder)
    model.save_pretrained(folder)
    if preprocessor is None or postprocessor is None:
        preprocessor, postprocessor = make_pre_post_processors(model.config)
    preprocessor.save_pretrained(folder)
    postprocessor.save_pretrained(folder)
    return folder


def _processors(folder: str | Path, config: Any, device: torch.device) -> tuple[Any, Any]:
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.processor.pipeline import ProcessorMigrationError
    from safetensors import SafetensorError

    try:
        return make_pre_post_processors(
            config,
            pretrained_path=str(folder),
            preprocessor_overrides={"device_processor": {"device": str(device)}},
        )
    except (OSError, ValueError, KeyError, TypeError, SafetensorError, ProcessorMigrationError) as exc:
        raise ValueError(
            f"{KIND}: cannot load the processor pipelines {list(PROCESSOR_FILES)} in {folder}: {exc}"
        ) from None


def check_folder(folder: str | Path, weights: bool = False) -> Any:
    """The SmolVLAConfig of a lerobot checkpoint folder, once the folder is known to be loadable: its config.json
    holds a smolvla policy whose backbone folder (vlm_model_name) exists, the processor pipelines are there and,
    with `weights`, model.safetensors is readable. Otherwise a ValueError naming the folder or the file."""
    from draccus.utils import DraccusException
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.smolvla import configuration_smolvla  # noqa: F401  (registers the "smolvla" type)

    path = Path(folder)
    config_file = path / CONFIG_FILE
    if not config_file.is_file():
        raise ValueError(f"{KIND}: no checkpoint folder at {str(folder)!r} ({CONFIG_FILE} missing)")
    try:
        raw = json.loads(config_file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{KIND}: cannot read {config_file}: {exc}") from None
    kind = raw.get("type") if isinstance(raw, dict) else None
    if kind is None:
        raise ValueError(f"{KIND}: {config_file} names no policy type (not a lerobot checkpoint)")
    if kind != KIND:
        raise ValueError(f"{KIND}: {folder} holds a policy of type {kind!r}, not {KIND!r} ({config_file})")
    missing = [name for name in PROCESSOR_FILES if not (path / name).is_file()]
    if missing:
        raise ValueError(
            f"{KIND}: checkpoint folder {folder} lacks {missing} (lerobot's processor pipelines; "
            "an older checkpoint needs lerobot's migrate_policy_normalization)"
        )
    try:
        config = PreTrainedConfig.from_pretrained(str(path))
    except (OSError, ValueError, KeyError, TypeError, DraccusException) as exc:
        raise ValueError(f"{KIND}: cannot read {config_file}: {exc}") from None
    backbone = Path(config.vlm_model_name)
    if not (backbone / CONFIG_FILE).is_file():
        what = f"has no {CONFIG_FILE}" if backbone.is_dir() else "does not exist"
        raise ValueError(
            f"{KIND}: the backbone folder {config.vlm_model_name!r} (vlm_model_name in {config_file}) {what}; "
            "nothing is downloaded, so it must be a local folder"
        )
    if weights:
        _check_weights(path / WEIGHTS_FILE)
    return config


def _check_weights(file: Path) -> None:
    from safetensors import SafetensorError, safe_open

    if not file.is_file():
        raise ValueError(f"{KIND}: {file} missing (the checkpoint's weights)")
    try:
        with safe_open(str(file), framework="pt") as weights:
            weights.keys()
    except (OSError, SafetensorError) as exc:
        raise ValueError(f"{KIND}: {file} is not a readable safetensors file: {exc}") from None


def model_state_dim(config: Any) -> int:
    """Values in the model's `observation.state` (0 when it reads none)."""
    feature = config.robot_state_feature
    return int(np.prod(feature.shape)) if feature is not None else 0


def model_cameras(config: Any) -> list[str]:
    """The lerobot camera names the model reads (`observation.images.<name>`; lerobot's empty-camera slots aside)."""
    names = [key.removeprefix(f"{IMAGES}.") for key in config.image_features]
    return [name for name in names if not name.startswith("empty_camera_")]


def check_spec(spec: SmolVlaSpec, config: Any) -> None:
    """ValueError naming the spec's field unless it fits the model's config: actions, state and cameras."""
    where = f"the model in {spec.checkpoint}"
    if config.action_feature is None:
        raise ValueError(f"{KIND}: {where} declares no action feature")
    action_dim = int(config.action_feature.shape[0])
    if spec.action_dim != action_dim:
        raise ValueError(f"{KIND}: action_dim is {spec.action_dim}, {where} outputs {action_dim}")
    if action_dim > config.max_action_dim:
        raise ValueError(
            f"{KIND}: {where} outputs {action_dim} values, over its max_action_dim {config.max_action_dim}"
        )
    state_dim = model_state_dim(config)
    if state_dim > config.max_state_dim:
        raise ValueError(
            f"{KIND}: {where} reads {state_dim} state values, over its max_state_dim {config.max_state_dim}"
        )
    if state_dim and not spec.state_keys:
        raise ValueError(f"{KIND}: state_keys is empty, {where} reads a state of {state_dim} values")
    if spec.state_keys and not state_dim:
        raise ValueError(f"{KIND}: state_keys {spec.state_keys} given, {where} reads no state")
    cameras = model_cameras(config)
    unknown = sorted(set(spec.image_keys.values()) - set(cameras))
    if unknown:
        raise ValueError(f"{KIND}: image_keys names cameras {unknown}, {where} reads {cameras}")
    if cameras and not spec.image_keys:
        raise ValueError(f"{KIND}: image_keys is empty, {where} reads cameras {cameras}")


def load_checkpoint(folder: str | Path, device: str = "cpu") -> tuple[Any, Any, Any]:
    """(SmolVLAPolicy with the folder's weights, preprocessor, postprocessor): lerobot's own loading path."""
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from safetensors import SafetensorError

    dev = check_device(device)
    check_folder(folder, weights=True)
    try:
        model = SmolVLAPolicy.from_pretrained(str(folder))
    except (OSError, KeyError, TypeError, RuntimeError, SafetensorError) as exc:
        raise ValueError(f"{KIND}: cannot load {Path(folder) / WEIGHTS_FILE}: {exc}") from None
    model.to(dev).eval()
    pre, post = _processors(folder, model.config, dev)
    return model, pre, post


def _architecture(config: Any, folder: str | Path, device: torch.device) -> Any:
    """The folder's architecture (its checked `config`) with fresh weights (streamed tensors replace them)."""
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    config.load_vlm_weights = False  # weights come from the stream
    try:
        return SmolVLAPolicy(config).to(device).eval()
    except (OSError, KeyError, TypeError) as exc:
        raise ValueError(f"{KIND}: cannot build from {str(folder)!r}: {exc}") from None


def parse_spec(spec: learner_pb2.PolicySpec) -> SmolVlaSpec:
    try:
        return SmolVlaSpec.model_validate(json.loads(spec.config_json))
    except (json.JSONDecodeError, ValidationError) as exc:
        raise ValueError(f"{KIND} config_json: {exc}") from None


# --- the policy -----------------------------------------------------------------------------------


class SmolVlaPolicy(Policy):
    """SmolVLA chunks (B, chunk_size, action_dim); preprocess (tokenize, normalise) runs batched."""

    def __init__(
        self,
        spec: learner_pb2.PolicySpec,
        tensors: Mapping[str, np.ndarray] | None,
        version: int,
        device: str = "cpu",
        model: Any = None,
    ) -> None:
        self.spec, self.version = spec, int(version)
        self.params = parse_spec(spec)
        self.device = check_device(device)
        if model is None:
            config = check_folder(self.params.checkpoint)
            check_spec(self.params, config)  # before building what may be a large architecture
            model = _architecture(config, self.params.checkpoint, self.device)
        else:
            check_spec(self.params, model.config)
        self.model = model
        self.state_dim = model_state_dim(self.model.config)
        if tensors is not None:
            load_tensors(self.model, tensors)
            self.model.to(self.device).eval()
        self.pre, self.post = _processors(self.params.checkpoint, self.model.config, self.device)
        self.horizon = int(self.model.config.chunk_size)
        self.optional_obs_keys = [INSTRUCTION_KEY]
        self.obs_keys = [*self.params.image_keys, *self.params.state_keys]
        self._observation_keys = tuple([*self.obs_keys, INSTRUCTION_KEY])
        self._action_shape = (self.params.action_dim,)
        self._chunk_horizon = self.horizon
        self._low = np.asarray(self.params.action_low, np.float32)
        self._high = np.asarray(self.params.action_high, np.float32)

    @property
    def observation_keys(self) -> tuple[str, ...]:
        return self._observation_keys

    @property
    def action_shape(self) -> tuple[int, ...]:
        return self._action_shape

    @property
    def chunk_horizon(self) -> int:
        return self._chunk_horizon

    @property
    def image_shapes(self) -> dict[str, tuple[int | None, ...]]:
        return {key: (None, None, 3) for key in self.params.image_keys}  # lerobot's processor resizes them

    @classmethod
    def from_checkpoint(
        cls, folder: str | Path, spec: SmolVlaSpec | None = None, version: int = 0, device: str = "cpu"
    ) -> SmolVlaPolicy:
        """A policy with the folder's own weights (a downloaded pretrained checkpoint, or a saved one)."""
        if spec is None:
            raise ValueError("from_checkpoint needs the feature mapping (SmolVlaSpec)")
        spec = spec.model_copy(update={"checkpoint": str(folder)})
        check_spec(spec, check_folder(folder, weights=True))  # before loading the weights
        model, _, _ = load_checkpoint(folder, device)
        return cls(policy_spec(spec), None, version, device, model=model)

    def check_observation(self, observation: Mapping[str, np.ndarray]) -> None:
        """Cameras as `image_shapes`, and the state keys together hold the model's `observation.state` values."""
        super().check_observation(observation)
        values = sum(int(np.size(observation[k])) for k in self.params.state_keys if k in observation)
        if values != self.state_dim:
            raise ValueError(f"state {self.params.state_keys} has {values} values, the policy reads {self.state_dim}")

    def tensors(self) -> dict[str, np.ndarray]:
        """The weights as named raw arrays: what a weight set streams."""
        return module_tensors(self.model)

    def preprocess(self, observation: Mapping[str, np.ndarray], instructions: Sequence[str]) -> dict[str, Any]:
        missing = [k for k in self.obs_keys if k not in observation]
        if missing:
            raise ValueError(f"observation lacks {missing}")
        batch_size = len(next(iter(observation.values())))
        batch: dict[str, Any] = {}
        for key, camera in self.params.image_keys.items():
            img = torch.from_numpy(np.asarray(observation[key], dtype=np.uint8)).permute(0, 3, 1, 2)
            batch[f"{IMAGES}.{camera}"] = img.float().div_(255.0)
        parts = [np.asarray(observation[k], np.float32).reshape(batch_size, -1) for k in self.params.state_keys]
        state = np.concatenate(parts, axis=1) if parts else np.zeros((batch_size, 0), np.float32)
        if state.shape[1] != self.state_dim:  # lerobot would pad a short one silently
            raise ValueError(
                f"state {self.params.state_keys} has {state.shape[1]} values, the policy reads {self.state_dim}"
            )
        batch[STATE] = torch.from_numpy(state)
        from_obs = observation.get(INSTRUCTION_KEY)
        texts = []
        for i in range(batch_size):
            text = instructions[i] if i < len(instructions) else ""
            if not text and from_obs is not None:
                text = decode_instruction(np.asarray(from_obs[i]))
            texts.append(text or self.params.default_instruction)
        batch["task"] = texts
        return self.pre(batch)

    @torch.no_grad()
    def forward(self, prepared: dict[str, Any], deterministic: bool = False) -> np.ndarray:
        batch_size = int(prepared[STATE].shape[0])
        cfg = self.model.config
        noise = None
        if deterministic:  # the mean path: start the flow from zeros
            noise = torch.zeros(batch_size, cfg.chunk_size, cfg.max_action_dim, device=self.device)
        self.model.reset()  # no action queue across calls: every request gets a whole chunk
        chunk = self.post(self.model.predict_action_chunk(prepared, noise=noise))
        out = np.asarray(chunk.detach().cpu().numpy(), dtype=np.float32)  # action_dim checked at build
        return np.clip(out, self._low, self._high)

    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        return self.forward(self.preprocess(observation, []), deterministic)


register_policy(KIND, "lerobot SmolVLA from a local checkpoint folder; chunks from cameras, state and an instruction")(
    SmolVlaPolicy
)
