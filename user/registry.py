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
names a module to import). The built-in packages of every interface load before any entry point, so a
plug-in that registers a kind a built-in has is the one refused, the same way in every process. A module
that fails to import (an optional dependency is missing) is remembered and reported once, not fatal for
the others.
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
# Entry-point and interface modules that failed to import -> why. Global, not per interface: one entry point may
# register in several interfaces, and is reported once.
_OTHER_ERRORS: dict[str, str] = {}
_entry_points_loaded = False
_entry_points_done = False  # every entry point imported: lookups may skip the lock
_builtins_loading = False


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
        """Class decorator. ValueError when the kind has no description (neither given nor a docstring) or another
        class has it: built-ins load before any outside plug-in registers, so that is the one refused."""

        def deco(cls: type[T]) -> type[T]:
            if not (isinstance(cls, type) and issubclass(cls, self.base)):
                raise TypeError(f"{cls!r} registered as a {self.interface} does not subclass {self.base.__name__}")
            params = getattr(cls, "Params", PluginParams)
            if not (isinstance(params, type) and issubclass(params, PluginParams)):
                raise TypeError(f"{cls.__name__}.Params must subclass user.registry.PluginParams")
            text = (description or next(iter((cls.__doc__ or "").strip().splitlines()), "")).strip()
            if not text:  # `userctl plugins` lists one described line per kind
                raise ValueError(
                    f"{self.interface} kind {kind!r} ({_qualname(cls)}) has no description: "
                    "pass register(kind, description=...) or give the class a docstring"
                )
            if not _is_builtin(cls):
                _load_builtins()  # a plug-in imported before discovery must not take a built-in's kind
            existing = self._entries.get(kind)
            if existing is not None and existing.cls is not cls:
                raise ValueError(
                    f"{self.interface} kind {kind!r} is already registered by {_qualname(existing.cls)}; "
                    f"{_qualname(cls)} is refused"
                )
            self._entries[kind] = Entry(self.interface, kind, cls, params, text)
            return cls

        return deco

    # ------------------------------------------------------------------ discovery

    def discover(self) -> None:
        # Threads (weight subscribers building policies) may look up kinds at once: the first discovers
        # while the others wait, so no one sees a half-imported registry. Re-entrant: a plug-in module
        # that looks up kinds while being imported does not deadlock.
        if self._discovered and _entry_points_done:  # set only once every import finished
            return
        discover_all()

    def _load_package(self) -> None:
        """Import every module of this interface's package (its built-in plug-ins)."""
        try:
            pkg = importlib.import_module(self.package)
            for info in pkgutil.iter_modules(getattr(pkg, "__path__", []), prefix=f"{self.package}."):
                if error := _import(info.name):
                    self.import_errors[info.name] = error
                    log.debug("plug-in module not loaded", extra={"plugin_module": info.name, "error": error})
        except ImportError as exc:
            self.import_errors[self.package] = f"{type(exc).__name__}: {exc}"
        finally:
            self._discovered = True

    @property
    def all_import_errors(self) -> dict[str, str]:
        """This interface's package modules and the entry points that failed to import (a kind may be in either)."""
        return {**self.import_errors, **_OTHER_ERRORS}

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
            errors = self.all_import_errors
            hint = f"; not loaded: {errors}" if errors else ""
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


def _qualname(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _import(module: str) -> str | None:
    """None, or why `module` could not be imported (an optional dependency missing must not hide the others)."""
    try:
        importlib.import_module(module)
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def _is_builtin(cls: type) -> bool:
    return any(cls.__module__.startswith(f"{reg.package}.") for reg in list(Registry._all.values()))


def _load_builtins() -> None:
    """Every interface's built-in package, before any plug-in from outside registers (re-entrant: a no-op while
    loading, so built-in modules importing each other do not recurse)."""
    global _builtins_loading
    with _DISCOVERY_LOCK:
        if _builtins_loading:
            return
        _builtins_loading = True
        try:
            _import_interfaces()
            while pending := [reg for reg in list(Registry._all.values()) if not reg._discovered]:
                for reg in pending:
                    reg._load_package()
        finally:
            _builtins_loading = False


def _import_interfaces() -> None:
    """Importing an interface module creates its registry."""
    for module in INTERFACE_MODULES:
        if module not in _OTHER_ERRORS and (error := _import(module)):
            _OTHER_ERRORS[module] = error
            log.warning("interface module not importable", extra={"plugin_module": module, "error": error})


def _load_entry_points() -> None:
    """The `user.plugins` entry points, once per process, after the built-ins."""
    global _entry_points_loaded, _entry_points_done
    if _entry_points_loaded or _builtins_loading:  # a lookup while built-ins import: entry points wait for them
        return
    _entry_points_loaded = True
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        module = ep.value.split(":")[0]
        if error := _import(module):
            _OTHER_ERRORS[module] = error
            log.warning("plug-in entry point not loaded", extra={"plugin_module": module, "error": error})
    _entry_points_done = True


def discover_all() -> None:
    """Built-ins of every interface, then the entry points (what any registry's first lookup does)."""
    with _DISCOVERY_LOCK:
        _load_builtins()
        _load_entry_points()


def import_errors() -> dict[str, str]:
    """Every plug-in module that failed to import -> why, each module once (for `userctl plugins`)."""
    discover_all()
    errors: dict[str, str] = {}
    for reg in registries():
        errors.update(reg.import_errors)
    return {**errors, **_OTHER_ERRORS}


def registries() -> Iterator[Registry[Any]]:
    """Every interface's registry, for `userctl plugins`."""
    _import_interfaces()
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
