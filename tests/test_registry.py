"""The registry: names from installed entry points only (the built-ins are declared in
pyproject.toml like any plug-in), lazy imports, clear errors, and third-party plug-ins found
through a real (temporary) installed distribution."""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap
import tomllib
import uuid
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from gateway import registry
from gateway.config import ConfigError, embedded_default, parse

REPO = Path(__file__).resolve().parents[1]


GROUPS = (registry.BACKEND_GROUP, registry.SOURCE_GROUP, registry.COMMAND_GROUP,
          registry.BACKEND_OPTIONS_GROUP, registry.SOURCE_OPTIONS_GROUP)


@pytest.mark.parametrize("group", GROUPS)
def test_the_installed_entry_points_are_the_ones_pyproject_declares(group: str) -> None:
    """pyproject.toml is the one list of built-ins; the installed metadata must carry it
    (stale after an edit of pyproject.toml until the package is installed again)."""
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["entry-points"]
    ours = {ep.name: ep.value for ep in entry_points(group=group)
            if ep.dist is not None and ep.dist.name == "aurora-gateway"}
    assert ours == declared[group], (
        f"installed {group} entry points differ from pyproject.toml: pip install -e .")


def test_names_are_exactly_the_installed_entry_points() -> None:
    installed = {ep.name: ep.value for ep in entry_points(group=registry.BACKEND_GROUP)}
    names = registry.names(registry.BACKEND_GROUP)
    assert names == installed
    assert names["console"] == "backends.console:ConsoleBackend"
    assert registry.backend_names() == sorted(installed)


def test_without_the_package_metadata_the_error_says_to_install_it(tmp_path: Path) -> None:
    """The sources on sys.path but not installed (no site-packages, no egg-info): nothing is
    registered, and the error says what to do."""
    (tmp_path / "gateway").symlink_to(REPO / "gateway")
    code = textwrap.dedent("""
        from gateway import registry as r
        print(r.backend_names())
        try:
            r.load(r.BACKEND_GROUP, "mavlink")
        except r.RegistryError as exc:
            print(exc)
    """)
    out = subprocess.run([sys.executable, "-S", "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60, check=True).stdout.splitlines()
    assert out[0] == "[]"
    assert out[1].startswith("unknown backend 'mavlink'; available: none (")
    assert "pip install -e ." in out[1]


def test_source_names_include_sim_serial_and_replay() -> None:
    assert {"sim", "serial", "replay"} <= set(registry.source_names())


def test_load_returns_the_registered_class() -> None:
    from backends.console import ConsoleBackend
    from gateway.sources.sim import SimSource

    assert registry.load(registry.BACKEND_GROUP, "console") is ConsoleBackend
    assert registry.load(registry.SOURCE_GROUP, "sim") is SimSource


def test_load_of_an_unknown_name_lists_what_is_available() -> None:
    with pytest.raises(registry.RegistryError) as info:
        registry.load(registry.BACKEND_GROUP, "teleporter")
    message = str(info.value)
    assert "unknown backend 'teleporter'" in message
    assert "console" in message
    with pytest.raises(LookupError, match=r"unknown source 'x'; available: .*sim"):
        registry.load(registry.SOURCE_GROUP, "x")


def test_importing_the_registry_imports_no_backend() -> None:
    code = textwrap.dedent("""
        import sys
        import gateway.registry as r
        import gateway.config
        r.names(r.BACKEND_GROUP)
        print("before", "backends.console" in sys.modules)
        r.load(r.BACKEND_GROUP, "console")
        print("after", "backends.console" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60, check=True).stdout.split("\n")
    assert out[:2] == ["before False", "after True"]


def test_every_builtin_backends_flags_load_without_importing_a_backend() -> None:
    code = textwrap.dedent("""
        import sys
        from gateway import registry as r
        flags = {n: r.load_flags(n) for n in r.backend_names()}
        sources = {n: r.load_source_options(n) for n in r.source_names()}
        print(sorted(n for n, f in flags.items() if not f.__name__.endswith("Options")))
        print(sorted(m for m in sys.modules if m.split(".")[0] in ("pymavlink", "zenoh")
                     or m == "dialects.aurora_mavlink"
                     or m.startswith("backends.") and m.endswith((".backend", ".source"))))
        print(sorted(n for n, o in sources.items() if not o.__name__.endswith("Options")))
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60, check=True).stdout.splitlines()
    assert out[0] == "['console']"  # no options entry: its class (light) is the fallback
    assert out[1] == "[]"
    assert out[2] == "[]"  # every source's options come from a light module


def test_load_flags_prefers_the_flags_entry_and_falls_back_to_the_class() -> None:
    from backends.console import ConsoleBackend
    from backends.mavlink.options import MavlinkOptions, MavlinkSourceOptions

    assert registry.load_flags("mavlink") is MavlinkOptions
    assert registry.load_flags("console") is ConsoleBackend
    assert registry.load_source_options("mavlink") is MavlinkSourceOptions
    with pytest.raises(registry.RegistryError, match="unknown backend 'teleporter'"):
        registry.load_flags("teleporter")


def test_parse_keep_drops_a_backend_before_importing_or_validating_it(
    plugin: tuple[str, str, str],
) -> None:
    _, broken, _ = plugin
    asked: list[str] = []

    def keep(name: str) -> bool:
        asked.append(name)
        return name == "console"

    cfg = parse({"backends": {broken: {}, "console": {}}}, keep)
    assert [p.name for p in cfg.backends] == ["console"]
    assert asked == [broken, "console"]
    assert [p.name for p in embedded_default(lambda n: n == "console").backends] == ["console"]


# -- third-party plug-ins, installed for real on a temporary sys.path entry -------------------


@pytest.fixture
def plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Install a distribution declaring a working and a broken backend; yields their names."""
    tag = uuid.uuid4().hex[:8]
    good, broken, missing = f"fancy{tag}", f"broken{tag}", f"missing{tag}"
    (tmp_path / f"{good}_mod.py").write_text(textwrap.dedent(f"""
        from gateway.backend import Backend
        from gateway.config import Key, Schema
        class FancyBackend(Backend):
            NAME = "{good}"
            CONFIG = Schema(level=Key(int, 0, "how fancy"))
            EMBEDDED_DEFAULT = None
            def __init__(self, name=None, level=0):
                super().__init__(name)
                self.level = level
            @classmethod
            def add_cli_arguments(cls, parser):
                parser.add_argument("--{good}-level", type=int, dest="fancy_level")
            @classmethod
            def cli_options(cls, args):
                return None if args.fancy_level is None else {{"level": args.fancy_level}}
    """))
    (tmp_path / f"{broken}_mod.py").write_text("raise RuntimeError('plug-in is broken')\n")
    dist = tmp_path / f"aurora_plugin_{tag}-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: aurora-plugin-{tag}\n"
                                   "Version: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[aurora_gateway.backends]\n"
        f"{good} = {good}_mod:FancyBackend\n"
        f"{broken} = {broken}_mod:Whatever\n"
        f"{missing} = no_such_module_{tag}:Backend\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    registry._installed.cache_clear()  # the entry points are read once a run: read them again
    yield good, broken, missing
    registry._installed.cache_clear()
    for mod in (f"{good}_mod", f"{broken}_mod"):
        sys.modules.pop(mod, None)


def test_an_installed_plugin_is_found_and_loaded_by_name(plugin: tuple[str, str, str]) -> None:
    good, _, _ = plugin
    assert good in registry.backend_names()
    assert "console" in registry.backend_names()
    cls = registry.load(registry.BACKEND_GROUP, good)
    assert cls.__name__ == "FancyBackend"
    assert cls().name == good
    assert parse({"backends": {good: {}}}).backends[0].cls is cls


@pytest.mark.parametrize("which", [1, 2], ids=["raises-on-import", "module-missing"])
def test_a_plugin_that_fails_to_import_is_a_registry_error(plugin: tuple[str, str, str],
                                                           which: int) -> None:
    name = plugin[which]
    with pytest.raises(registry.RegistryError, match=rf"'{name}' .* failed to import"):
        registry.load(registry.BACKEND_GROUP, name)
    with pytest.raises(ConfigError, match=rf"^backends\.{name}\.type: .*failed to import"):
        parse({"backends": {name: {}}})


def test_a_broken_plugin_does_not_stop_the_embedded_default(
    plugin: tuple[str, str, str],
) -> None:
    good, broken, _ = plugin
    cfg = embedded_default()
    types = [p.type for p in cfg.backends]
    assert "console" in types
    assert broken not in types
    assert good not in types  # EMBEDDED_DEFAULT = None keeps it out of the default run


def test_a_plugin_with_no_flags_entry_has_its_classmethods_used(
    plugin: tuple[str, str, str],
) -> None:
    """The flags entry point is optional: a third-party backend's classmethods still add
    its flags to ``run`` and turn them into its options."""
    from gateway.commands import cli

    good, _, _ = plugin
    args = cli.build_parser().parse_args(["run", f"--{good}-level", "3", "--only", good])
    cfg = cli.config_from_args(args)
    assert [(p.name, p.options) for p in cfg.backends] == [(good, {"level": 3})]


def test_a_signal_while_a_module_executes_is_the_signal_not_an_import_error(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C while ``run`` imports the options modules (a dataclass being created wraps it:
    "RuntimeError: Error calling __set_name__ …") reaches the command, which exits 130; it
    was once reported as that module failing to import, and the run went on."""
    module = f"interrupted_{uuid.uuid4().hex}"
    (tmp_path / f"{module}.py").write_text(
        "raise RuntimeError('Error calling __set_name__') from KeyboardInterrupt()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "names", lambda group: {"x": f"{module}:Options"})
    with pytest.raises(RuntimeError) as info:
        registry.load(registry.BACKEND_OPTIONS_GROUP, "x")
    assert not isinstance(info.value, registry.RegistryError)
    assert isinstance(info.value.__cause__, KeyboardInterrupt)
