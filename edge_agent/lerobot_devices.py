"""Build lerobot robots and teleoperators from a type name and a config mapping.

lerobot keeps its device configs in draccus choice registries (`RobotConfig.register_subclass("so101_follower")`).
A type is looked up there after importing lerobot's device packages (they register on import); the
config mapping is decoded by draccus, so nested configs (cameras) work as in lerobot's own CLI. The
device class is the registered subclass of the device ABC whose `config_class` is that config (which
finds devices defined outside lerobot too), else lerobot's own factory.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Mapping
from typing import Any


def _subclasses(base: type) -> list[type]:
    found, todo = [], [base]
    while todo:
        for sub in todo.pop().__subclasses__():
            found.append(sub)
            todo.append(sub)
    return found


def _import_device_packages(package: str) -> None:
    pkg = importlib.import_module(package)
    for info in pkgutil.iter_modules(pkg.__path__, prefix=f"{package}."):
        if info.ispkg:
            try:
                importlib.import_module(info.name)
            except Exception:  # a device whose SDK is not installed; the others still register
                continue


def _config(config_base: Any, package: str, type_name: str, raw: Mapping[str, Any]) -> Any:
    import draccus

    try:
        config_cls = config_base.get_choice_class(type_name)
    except KeyError:
        _import_device_packages(package)
        try:
            config_cls = config_base.get_choice_class(type_name)
        except KeyError:
            known = sorted(config_base.get_known_choices())
            raise ValueError(f"unknown lerobot type {type_name!r}; known: {known}") from None
    return draccus.decode(config_cls, dict(raw))


def _device(base: type, config: Any, factory: Any) -> Any:
    for cls in _subclasses(base):
        if getattr(cls, "config_class", None) is type(config) and not getattr(cls, "__abstractmethods__", None):
            return cls(config)
    return factory(config)


def make_lerobot_robot(type_name: str, raw_config: Mapping[str, Any]) -> Any:
    from lerobot.robots import Robot, RobotConfig, make_robot_from_config

    return _device(Robot, _config(RobotConfig, "lerobot.robots", type_name, raw_config), make_robot_from_config)


def make_lerobot_teleoperator(type_name: str, raw_config: Mapping[str, Any]) -> Any:
    from lerobot.teleoperators import Teleoperator, TeleoperatorConfig, make_teleoperator_from_config

    config = _config(TeleoperatorConfig, "lerobot.teleoperators", type_name, raw_config)
    return _device(Teleoperator, config, make_teleoperator_from_config)
