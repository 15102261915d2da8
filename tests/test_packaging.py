"""The package as users install it: its data files are package data, its extras are the ones
the code names, and an optional dependency that is missing is one line naming its extra, exit 2.

A missing module is simulated in a subprocess by ``sys.modules[name] = None`` before the
command line runs: ``import name`` then raises the ``ModuleNotFoundError`` a base install
raises, through the real code path (entry points, registry, configuration, command).  The
wheel itself, built and installed outside the checkout, is checked by ``tools/check_wheel.py``
(``make wheel-check``, run by ``.ci/run``).
"""

from __future__ import annotations

import fnmatch
import os
import re
import subprocess
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

from gateway import recording, registry
from gateway.flight import FlightModel
from gateway.sources.sim import flight_messages
from gateway.wire import encode

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
EXTRAS = PYPROJECT["project"]["optional-dependencies"]
#: extras that install no optional backend or command of their own
AGGREGATES = {"all", "test"}


def _dist(requirement: str) -> str:
    """A requirement's distribution name, normalized (PEP 503)."""
    match = re.match(r"[A-Za-z0-9._-]+", requirement)
    assert match, requirement
    return re.sub(r"[-_.]+", "-", match.group()).lower()


def _self_extras(requirement: str) -> set[str]:
    """The extras of a requirement on this project itself (``aurora-gateway[a,b]``)."""
    match = re.fullmatch(r"aurora-gateway\[([a-z0-9,_-]+)\]", requirement.replace(" ", ""))
    return set(match.group(1).split(",")) if match else set()


# -- extras ------------------------------------------------------------------------------------

def test_every_module_of_the_table_comes_from_its_extra() -> None:
    """EXTRA_OF_MODULE agrees with pyproject.toml: each module is installed (here, where every
    extra is) by a distribution that its extra requires."""
    provided = packages_distributions()
    for module, extra in registry.EXTRA_OF_MODULE.items():
        assert extra in EXTRAS and extra not in AGGREGATES, (module, extra)
        dists = {_dist(d) for d in provided.get(module, [])}
        wanted = {_dist(r) for r in EXTRAS[extra]}
        assert dists & wanted, f"{module}: from {dists}, not from the {extra!r} extra {wanted}"


def test_every_extra_is_named_by_the_table_and_in_all() -> None:
    """Each optional extra has its libraries' modules in the table (else its absence would be
    a traceback), the ``all`` extra is every one of them, and ``test`` has ``all``."""
    provided = packages_distributions()
    by_dist: dict[str, set[str]] = {}
    for module, dists in provided.items():
        for d in dists:
            by_dist.setdefault(_dist(d), set()).add(module)
    optional = set(EXTRAS) - AGGREGATES
    for extra in optional:
        for req in EXTRAS[extra]:
            modules = by_dist.get(_dist(req), set())
            assert any(registry.EXTRA_OF_MODULE.get(m) == extra for m in modules), \
                f"{req} (extra {extra!r}): none of its modules {modules} is in EXTRA_OF_MODULE"
    assert set().union(*map(_self_extras, EXTRAS["all"])) == optional
    assert "all" in set().union(*map(_self_extras, EXTRAS["test"]))


def test_missing_extra_follows_the_cause_and_knows_only_the_table() -> None:
    try:
        try:
            raise ModuleNotFoundError("No module named 'h11'", name="h11")
        except ImportError as exc:
            raise ImportError("the http backend needs h11") from exc
    except ImportError as exc:
        assert registry.missing_extra(exc) == "http"
    try:
        try:
            raise ModuleNotFoundError("No module named 'mcap'", name="mcap")
        except ImportError:
            raise RuntimeError("handled: not the cause") from None
    except RuntimeError as exc:
        assert registry.missing_extra(exc) is None
    assert registry.missing_extra(ModuleNotFoundError(name="matplotlib.figure")) == "plot"
    assert registry.missing_extra(ModuleNotFoundError(name="nosuchmodule")) is None
    assert registry.missing_extra(ValueError("x")) is None


# -- package data --------------------------------------------------------------------------------

def test_every_data_file_of_the_packages_is_package_data() -> None:
    """A file under the packages that is not Python (an XML the code parses) is covered by a
    ``[tool.setuptools.package-data]`` pattern, or the wheel would lack it.  A backend's
    README is documentation, not data."""
    patterns = PYPROJECT["tool"]["setuptools"]["package-data"]
    listed = subprocess.run(["git", "ls-files", "gateway", "backends", "dialects"], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout.split()
    data = [p for p in listed if not p.endswith((".py", ".c"))  # (.c: ext-modules' sources)
            and not (p.endswith("README.md") and not p.startswith("dialects/"))]
    assert any(p.startswith("dialects/uavtalk/") for p in data)
    uncovered = []
    for path in data:
        parts = Path(path).parts
        covered = False
        for i in range(1, len(parts)):  # the package is any directory above the file
            package = ".".join(parts[:i])
            rest = "/".join(parts[i:])
            if any(fnmatch.fnmatchcase(rest, pat) for pat in patterns.get(package, ())):
                covered = True
        if not covered:
            uncovered.append(path)
    assert not uncovered, f"not package data (add to pyproject.toml): {uncovered}"


def test_the_files_for_the_user_exist() -> None:
    """``[tool.setuptools] data-files``: what an install puts in share/aurora-gateway/."""
    files = PYPROJECT["tool"]["setuptools"]["data-files"]["share/aurora-gateway"]
    assert "docs/foxglove-layout.json" in files
    for name in files:
        assert (ROOT / name).is_file(), name


# -- a missing optional dependency, through the command line -----------------------------------

SHIM = ("import sys\n"
        "for name in sys.argv[1].split(','):\n"
        "    sys.modules[name] = None  # import name: ModuleNotFoundError, as on a base install\n"
        "from gateway.commands.cli import console_main\n"
        "sys.argv = ['aurora-gateway', *sys.argv[2:]]\n"
        "console_main()  # as the console script: no interpreter teardown (Zenoh's threads)\n")


def without(modules: str, *argv: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", SHIM, modules, *map(str, argv)], cwd=cwd,
                          capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("packaging") / "flight.aur"
    with path.open("wb") as f:
        f.write(recording.HEADER)
        for t, msg in flight_messages(FlightModel(), rate_hz=10.0, status_hz=1.0, cycles=1):
            f.write(recording.encode_record(1_790_000_000.0 + t, encode(msg)))
    return path


def _one_line(proc: subprocess.CompletedProcess[str], what: str, extra: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"aurora-gateway: {what} needs the {extra!r} extra: "
        f"pip install 'aurora-gateway[{extra}]'"], proc.stderr


@pytest.mark.parametrize(("modules", "flag", "what", "extra"), [
    ("foxglove", "--foxglove", "backend foxglove", "foxglove"),
    ("h11,prometheus_client", "--http", "backend http", "http"),
])
def test_a_backend_flag_without_its_extra(tmp_path: Path, modules: str, flag: str, what: str,
                                          extra: str) -> None:
    proc = without(modules, "run", "--duration", "0", flag, "127.0.0.1:0", cwd=tmp_path)
    _one_line(proc, what, extra)


def test_plot_without_matplotlib(tmp_path: Path, flight: Path) -> None:
    proc = without("matplotlib", "plot", flight, "-o", tmp_path / "f.png", cwd=tmp_path)
    _one_line(proc, "plot", "plot")
    assert not (tmp_path / "f.png").exists()


def test_export_mcap_without_mcap(tmp_path: Path, flight: Path) -> None:
    proc = without("mcap", "export", flight, "--format", "mcap", "-o", tmp_path / "f.mcap",
                   cwd=tmp_path)
    _one_line(proc, "export", "mcap")
    # the other formats need no extra
    proc = without("mcap", "export", flight, "--format", "csv", "-o", tmp_path / "f.csv",
                   cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr


def test_check_config_without_an_extra(tmp_path: Path) -> None:
    """An enabled backend whose extra is missing is an error naming the extra, as ``run``
    says; a disabled one is checked by its options declaration alone (``enabled = false``:
    the example configuration on a base install)."""
    cfg = tmp_path / "fox.toml"
    cfg.write_text('[[sources]]\ntype = "sim"\n[backends.foxglove]\nport = 8765\n')
    proc = without("foxglove", "check-config", cfg, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"aurora-gateway check-config: {cfg}: backend foxglove needs the 'foxglove' extra: "
        "pip install 'aurora-gateway[foxglove]'"]
    proc = without("foxglove", "run", "-c", cfg, "--duration", "0", cwd=tmp_path)
    _one_line(proc, "backend foxglove", "foxglove")

    example = ROOT / "examples" / "gateway.toml"
    proc = without("foxglove,h11,prometheus_client", "check-config", example, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "# [backends.foxglove] enabled = false: checked, not run" in proc.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text('[[sources]]\ntype = "sim"\n[backends.console]\n'
                   '[backends.foxglove]\nenabled = false\nport = "x"\n')
    proc = without("foxglove", "check-config", bad, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        f"aurora-gateway check-config: {bad}: backends.foxglove.port: expected an integer, "
        "got 'x'"]


def test_the_embedded_default_leaves_out_what_is_not_installed(tmp_path: Path) -> None:
    proc = without("foxglove,h11", "run", "--duration", "0", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    started = next(ln for ln in proc.stderr.splitlines() if ": sources " in ln)
    assert "console" in started and "foxglove" not in started and "http" not in started


def test_a_plugin_command_without_its_extra(tmp_path: Path) -> None:
    """A command from the ``aurora_gateway.commands`` group whose module needs an extra at
    import: asked for, one line naming the extra, exit 2; ``--help`` lists the others."""
    plugins = tmp_path / "plugins"
    plugins.mkdir()
    (plugins / "fancy_cmd.py").write_text(
        "import matplotlib  # an extra's module, at import time\n"
        "def add_command(subparsers):\n"
        "    subparsers.add_parser('fancyplot')\n")
    dist = plugins / "aurora_fancy-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: aurora-fancy\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[aurora_gateway.commands]\nfancyplot = fancy_cmd:add_command\n")
    env = {**os.environ, "PYTHONPATH": str(plugins)}
    proc = subprocess.run([sys.executable, "-c", SHIM, "matplotlib", "fancyplot"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=60)
    _one_line(proc, "command fancyplot", "plot")
    proc = subprocess.run([sys.executable, "-c", SHIM, "matplotlib", "--help"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert " plot " in proc.stdout and "fancyplot" not in proc.stdout
