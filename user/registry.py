"""One registry helper for every plug-in interface (robot, task, teleoperator, policy, algorithm).

A plug-in is one class plus one decorator:

    @ROBOTS.register("sim_reach_arm", description="3-joint MuJoCo arm reaching a random target")
    class SimReachArm(Robot):
        class Params(PluginParams):
            control_rate_hz: float = 20.0

A config entry names the kind and gives its params; `build` validates them against the class's
`Params` model (pydantic, extra fields forbidden) and fails with the dotted field at start. Plug-ins
are found without an import list: every module of the interface's package is imported on first use,
and installed packages may add more through the `user.plugins` entry-point group (each entry point
names a module to import). A module that fails to import (an optional dependency is missing) is
remembered and reported, not fatal for the others.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import logging
import pkgutil
import threading
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "user.plugins"
_DISCOVERY_LOCK = threading.RLock()  # one lock for all registries: plug-in imports may touch several


class PluginParams(BaseModel):
    """Base of every plug-in's typed params: unknown keys are an error, not silently ignored."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class PluginError(ValueError):
    """A plug-in config is wrong: unknown kind or bad params. The message names the dotted field."""


@dataclass(frozen=True)
class Entry[T]:
    interface: str
    kind: str
    cls: type[T]
    params: type[PluginParams]
    description: str


class Registry[T]:
    """Kinds of one interface. `package` is imported module by module to find the built-in plug-ins."""

    _all: dict[str, Registry[Any]] = {}

    def __init__(self, interface: str, base: type[T], package: str) -> None:
        self.interface, self.base, self.package = interface, base, package
        self._entries: dict[str, Entry[T]] = {}
        self._discovered = False
        self.import_errors: dict[str, str] = {}  # module -> why it could not be imported
        Registry._all[interface] = self

    def register(self, kind: str, description: str | None = None) -> Callable[[type[T]], type[T]]:
        def deco(cls: type[T]) -> type[T]:
            if not (isinstance(cls, type) and issubclass(cls, self.base)):
                raise TypeError(f"{cls!r} registered as a {self.interface} does not subclass {self.base.__name__}")
            params = getattr(cls, "Params", PluginParams)
            if not (isinstance(params, type) and issubclass(params, PluginParams)):
                raise TypeError(f"{cls.__name__}.Params must subclass user.registry.PluginParams")
            text = description or next(iter((cls.__doc__ or "").strip().splitlines()), "")
            existing = self._entries.get(kind)
            if existing is not None and existing.cls is not cls:
                raise ValueError(f"{self.interface} kind {kind!r} is already registered by {existing.cls.__name__}")
            self._entries[kind] = Entry(self.interface, kind, cls, params, text)
            return cls

        return deco

    # ------------------------------------------------------------------ discovery

    def discover(self) -> None:
        # Threads (weight subscribers building policies) may look up kinds at once: the first discovers
        # while the others wait, so no one sees a half-imported registry. Re-entrant: a plug-in module
        # that looks up kinds while being imported does not deadlock.
        with _DISCOVERY_LOCK:
            if self._discovered:
                return
            self._discovered = True
            try:
                pkg = importlib.import_module(self.package)
            except ImportError as exc:
                self.import_errors[self.package] = str(exc)
                return
            for info in pkgutil.iter_modules(getattr(pkg, "__path__", []), prefix=f"{self.package}."):
                self._import(info.name)
            for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
                self._import(ep.value.split(":")[0])

    def _import(self, module: str) -> None:
        try:
            importlib.import_module(module)
        except Exception as exc:  # an optional dependency missing must not hide the other plug-ins
            self.import_errors[module] = f"{type(exc).__name__}: {exc}"
            log.debug("plug-in module not loaded", extra={"module": module, "error": str(exc)})

    # ------------------------------------------------------------------ lookup and build

    def entries(self) -> list[Entry[T]]:
        self.discover()
        return [self._entries[k] for k in sorted(self._entries)]

    def kinds(self) -> list[str]:
        return [e.kind for e in self.entries()]

    def get(self, kind: str, where: str = "kind") -> Entry[T]:
        self.discover()
        try:
            return self._entries[kind]
        except KeyError:
            hint = f"; not loaded: {self.import_errors}" if self.import_errors else ""
            raise PluginError(
                f"{where}: unknown {self.interface} kind {kind!r}; known: {sorted(self._entries)}{hint}"
            ) from None

    def params(self, kind: str, raw: Mapping[str, Any] | None, where: str = "params") -> PluginParams:
        """Validate a config's params for `kind`; errors name `where.<field>`."""
        entry = self.get(kind, where.rsplit(".", 1)[0] + ".kind" if "." in where else "kind")
        try:
            return entry.params.model_validate(dict(raw or {}))
        except ValidationError as exc:
            msgs = []
            for err in exc.errors():
                loc = ".".join(str(p) for p in err["loc"])
                msgs.append(f"{where}.{loc}: {err['msg']}" if loc else f"{where}: {err['msg']}")
            raise PluginError("; ".join(msgs)) from None

    def build(self, kind: str, raw_params: Mapping[str, Any] | None = None, where: str = "params", **context: Any) -> T:
        """Instantiate `kind` as cls(params, **context) after validating its params."""
        params = self.params(kind, raw_params, where)
        return self.get(kind).cls(params, **context)  # type: ignore[call-arg]


def registries() -> Iterator[Registry[Any]]:
    """Every interface's registry, for `userctl plugins`. Importing the interface modules creates them."""
    for module in INTERFACE_MODULES:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            log.warning("interface module not importable", extra={"module": module, "error": str(exc)})
    yield from (Registry._all[name] for name in sorted(Registry._all))


# The modules that define the interfaces (each creates one Registry). Plug-ins themselves need no list.
INTERFACE_MODULES = (
    "edge_agent.robot",
    "edge_agent.task",
    "edge_agent.teleop",
    "user.policy",
    "cloud_learner.algorithm",
)


def plugin_lines() -> list[str]:
    """Stable listing: one `interface kind description` line per registered kind."""
    lines = []
    for reg in registries():
        for entry in reg.entries():
            lines.append(f"{reg.interface} {entry.kind} {entry.description}".rstrip())
    return lines


def params_lines(interface: str, kind: str) -> list[str]:
    """What a config entry of this kind may set: one `name  type  default  description` line per param.
    PluginError naming the known interfaces or kinds when there is no such plug-in."""
    found = {reg.interface: reg for reg in registries()}
    if interface not in found:
        raise PluginError(f"unknown interface {interface!r}; known: {sorted(found)}")
    entry = found[interface].get(kind)
    lines = [f"{interface} {kind}: {entry.description}", f"params ({len(entry.params.model_fields)}):"]
    rows = [
        (name, _type_name(field.annotation), _default(field), field.description or "")
        for name, field in entry.params.model_fields.items()
    ]
    widths = [max((len(row[i]) for row in rows), default=0) for i in range(3)]
    for row in rows:
        lines.append("  " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=False)) + "  " + row[3])
    return [line.rstrip() for line in lines]


def _type_name(annotation: Any) -> str:
    """A short readable type: constraints (Annotated metadata) left out, as the description states them."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin is typing.Literal:
        return " | ".join(str(a) for a in args)
    if annotation is type(None):
        return "None"
    if isinstance(annotation, type) and not args:
        return annotation.__name__
    if origin is types.UnionType or origin is typing.Union:
        return " | ".join(_type_name(a) for a in args)
    if origin is not None and args:
        name = getattr(origin, "__name__", str(origin).replace("typing.", ""))
        return f"{name}[{', '.join(_type_name(a) for a in args)}]"
    return str(annotation).replace("typing.", "")


def _default(field: Any) -> str:
    if field.is_required():
        return "(required)"
    value = field.get_default(call_default_factory=True)
    return json.dumps(value) if isinstance(value, (dict, list, str)) else str(value)
