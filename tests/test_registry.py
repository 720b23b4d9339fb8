"""user.registry: typed params fail naming the dotted field, discovery needs no import list, and a
module that fails to import is reported without hiding the others."""

from __future__ import annotations

import subprocess
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


def test_a_kind_without_a_description_or_a_duplicate_is_refused_naming_both(registry: Registry[Widget]) -> None:
    with pytest.raises(ValueError, match=r"widget-test kind 'bare' \(tests\.test_registry\.Bare\) has no description"):
        registry.register("bare")(type("Bare", (Widget,), {"__module__": __name__}))
    registry.discover()
    other = type("Other", (Widget,), {"__module__": __name__, "__doc__": "Another gear."})
    with pytest.raises(ValueError, match=r"already registered by widgets_pkg_for_test\.gear\.Gear; .*Other is refused"):
        registry.register("gear")(other)
    assert registry.get("gear").cls.__name__ == "Gear"


# --------------------------------------------------------------------------- entry points, in fresh processes

CLASH = {
    "dup": """
        from edge_agent.task import TASKS, Outcome, Task

        @TASKS.register("reach", description="clash: my own reach")
        class MyReach(Task):
            def evaluate(self, observation, action, next_observation):
                return Outcome(reward=1.0)
        """,
    "broken": "import a_module_that_does_not_exist_anywhere\n",
    "nodesc": """
        from edge_agent.task import TASKS, Outcome, Task

        @TASKS.register("clash_nodesc")
        class NoDesc(Task):
            def evaluate(self, observation, action, next_observation):
                return Outcome(reward=0.0)
        """,
}


@pytest.fixture
def clash_env(tmp_path: Path) -> dict[str, str]:
    """An installed package (a dist-info with `user.plugins` entry points) whose modules take a built-in's kind,
    fail to import, register without a description, or do not exist."""
    import os

    _package(tmp_path, "clashplug", CLASH)
    info = tmp_path / "clashplug-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: clashplug\nVersion: 0.1\n")
    points = {**{name: f"clashplug.{name}" for name in CLASH}, "typo": "clashplug.does_not_exist"}
    (info / "entry_points.txt").write_text("[user.plugins]\n" + "".join(f"{k} = {v}\n" for k, v in points.items()))
    root = str(Path(__file__).resolve().parents[1])
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), root]), "MUJOCO_GL": "egl"}


def _python(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True, timeout=300, check=False)


def test_userctl_plugins_keeps_built_ins_and_reports_each_failed_module_once(clash_env: dict[str, str]) -> None:
    done = _python(clash_env, "-m", "user.cli", "plugins")
    assert done.returncode == 1, done.stderr
    out = done.stdout.splitlines()
    assert "task reach Bring the end-effector within success_radius of the target (dense progress reward)." in out
    for kind in ("robot sim_reach_arm ", "robot lang_reach_arm ", "teleoperator lang_reach_expert "):
        assert any(line.startswith(kind) for line in out), kind
    assert not any("clash" in line for line in out)
    errors = done.stderr.splitlines()
    assert errors == [
        f"userctl plugins: module clashplug.{module} not loaded: {why}"
        for module, why in [
            ("broken", "ModuleNotFoundError: No module named 'a_module_that_does_not_exist_anywhere'"),
            ("does_not_exist", "ModuleNotFoundError: No module named 'clashplug.does_not_exist'"),
            (
                "dup",
                "ValueError: task kind 'reach' is already registered by edge_agent.tasks.reach.ReachTask; "
                "clashplug.dup.MyReach is refused",
            ),
            (
                "nodesc",
                "ValueError: task kind 'clash_nodesc' (clashplug.nodesc.NoDesc) has no description: "
                "pass register(kind, description=...) or give the class a docstring",
            ),
        ]
    ]


@pytest.mark.parametrize(
    "first",
    [
        "from edge_agent.robot import ROBOTS; ROBOTS.kinds()",
        "import contextlib\nwith contextlib.suppress(ValueError): import clashplug.dup",
    ],
)
def test_the_built_in_wins_whichever_is_looked_up_or_imported_first(clash_env: dict[str, str], first: str) -> None:
    """The edge looks robots up first, `userctl plugins` every interface in turn, a script may import a plug-in
    module itself: the built-in `reach` stays, in every process."""
    done = _python(
        clash_env, "-c", f"{first}\nfrom edge_agent.task import TASKS\nprint(TASKS.get('reach').cls.__module__)"
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["edge_agent.tasks.reach"]
