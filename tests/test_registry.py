"""user.registry: typed params fail naming the dotted field, discovery needs no import list, and a
module that fails to import is reported without hiding the others."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from user.registry import PluginError, PluginParams, Registry


class Widget:
    def __init__(self, params: PluginParams, **context: object) -> None:
        self.params, self.context = params, context


def _package(tmp_path: Path, name: str, modules: dict[str, str]) -> str:
    pkg = tmp_path / name
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for mod, body in modules.items():
        (pkg / f"{mod}.py").write_text(textwrap.dedent(body))
    return name


@pytest.fixture
def registry(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Registry[Widget]:
    monkeypatch.syspath_prepend(str(tmp_path))
    reg: Registry[Widget] = Registry("widget-test", Widget, "widgets_pkg_for_test")
    sys.modules["tests._widget_registry"] = type(sys)("tests._widget_registry")
    sys.modules["tests._widget_registry"].REG = reg  # type: ignore[attr-defined]
    sys.modules["tests._widget_registry"].Widget = Widget  # type: ignore[attr-defined]
    _package(
        tmp_path,
        "widgets_pkg_for_test",
        {
            "gear": """
                from user.registry import PluginParams
                from tests._widget_registry import REG, Widget

                @REG.register("gear")
                class Gear(Widget):
                    '''A toothed wheel.'''
                    class Params(PluginParams):
                        teeth: int = 12
                """,
            "broken": "import a_module_that_does_not_exist_anywhere\n",
        },
    )
    yield reg
    for name in [m for m in sys.modules if m.startswith("widgets_pkg_for_test")]:
        del sys.modules[name]
    del sys.modules["tests._widget_registry"]
    Registry._all.pop("widget-test", None)


def test_plugins_are_found_without_an_import_list(registry: Registry[Widget]) -> None:
    assert registry.kinds() == ["gear"]
    assert registry.get("gear").description == "A toothed wheel."


def test_a_module_that_fails_to_import_is_reported_not_fatal(registry: Registry[Widget]) -> None:
    registry.discover()
    assert "widgets_pkg_for_test.broken" in registry.import_errors
    assert "gear" in registry.kinds()


def test_build_validates_params_and_passes_context(registry: Registry[Widget]) -> None:
    gear = registry.build("gear", {"teeth": 30}, where="x.params", robot="arm-0")
    assert gear.params.teeth == 30  # type: ignore[attr-defined]
    assert gear.context == {"robot": "arm-0"}


@pytest.mark.parametrize(
    ("raw", "fragment"),
    [({"teeth": "many"}, "edge.robots.0.params.teeth"), ({"teef": 3}, "edge.robots.0.params.teef")],
)
def test_a_bad_param_fails_naming_the_dotted_field(registry: Registry[Widget], raw: dict, fragment: str) -> None:
    with pytest.raises(PluginError, match=fragment.replace(".", r"\.")):
        registry.build("gear", raw, where="edge.robots.0.params")


def test_an_unknown_kind_lists_the_known_ones(registry: Registry[Widget]) -> None:
    with pytest.raises(PluginError, match=r"unknown widget-test kind 'cog'.*gear"):
        registry.get("cog")


def test_a_class_of_the_wrong_interface_is_refused(registry: Registry[Widget]) -> None:
    with pytest.raises(TypeError, match="does not subclass Widget"):
        registry.register("nope")(int)  # type: ignore[arg-type]


def test_param_types_print_short_without_constraint_reprs() -> None:
    """`userctl plugins INTERFACE KIND` prints one line per param: types as a user writes them."""
    from typing import Annotated, Literal

    from pydantic import Field, StringConstraints

    from user.registry import _type_name

    name = Annotated[str, StringConstraints(pattern="^[a-z]+$")]
    share = Annotated[float, Field(gt=0)]
    assert _type_name(dict[name, share]) == "dict[str, float]"
    assert _type_name(list[str] | None) == "list[str] | None"
    assert _type_name(Literal["min", "mean"]) == "min | mean"
    assert _type_name(int) == "int"
