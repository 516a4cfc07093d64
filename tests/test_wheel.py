"""The harness installed from its wheel (not editable), used from a folder outside the checkout: the wheel carries
the configs (``harness.configs``) and the shipped reference results (``harness.shipped_references``), and the
installed code reads them: profiles, protocols, ``--config configs/...``, ``harness synth``, ``prepare``, a run and a
report against ``--reference-results shipped``.

The wheel is built from a copy of the checkout (so a stale ``build/`` cannot leak into it) and installed with
``pip install --no-deps --target``; the commands run with that folder first on ``PYTHONPATH``, which wins over the
editable install of the test environment (its finder is the last on ``sys.meta_path``), and each command's own
``harness.__file__`` is checked to be the installed one."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml

from report_fixtures import TINY_RUN

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
#: Top-level folders of the checkout that are not sources (outputs, environments, data).
NOT_SOURCES = {".git", ".venv", "build", "dist", "results", "cache", "data", "reports", ".pytest_cache"}
#: Where the shipped references are, inside an installed harness.
SHIPPED_MANIFEST = "harness/shipped_references/m3t-synth-benchmark/references.json"


def _copy_sources(dest: Path) -> None:
    def ignore(folder: str, names: list[str]) -> set[str]:
        skip = {n for n in names if n == "__pycache__" or n.endswith(".egg-info")}
        return skip | (NOT_SOURCES & set(names) if Path(folder) == REPO else set())

    shutil.copytree(REPO, dest, ignore=ignore)


@pytest.fixture(scope="module")
def wheel_install(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the wheel, the folder it is installed into)."""
    if importlib.util.find_spec("setuptools") is None:
        pytest.skip("building the wheel without build isolation needs setuptools in the test environment")
    tmp = tmp_path_factory.mktemp("wheel")
    src, wheels, site = tmp / "src", tmp / "wheels", tmp / "site"
    _copy_sources(src)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    for args in (
        ["wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(src)],
        ["install", "--no-deps", "--no-compile", "--target", str(site)],
    ):
        if args[0] == "install":
            args.append(str(next(wheels.glob("rgbt_harness-*.whl"))))
        out = subprocess.run(pip + args, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, f"pip {args[0]} failed:\n{out.stdout}\n{out.stderr}"
    return next(wheels.glob("rgbt_harness-*.whl")), site


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """An empty working folder outside the checkout."""
    work = tmp_path / "work"
    work.mkdir()
    assert not work.resolve().is_relative_to(REPO)
    return work


def _env(site: Path, work: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HARNESS_") and k != "PYTHONPATH"}
    return {
        **env,
        "PYTHONPATH": str(site),
        "HARNESS_DISABLE_PLUGIN_AUTOLOAD": "1",
        "HARNESS_DATA": str(work / "data"),
        "HARNESS_CACHE": str(work / "cache"),
    }


def _python(site: Path, work: Path, code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=work, env=_env(site, work), timeout=120
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


def _harness(site: Path, work: Path, *args: str, code: int | None = 0) -> subprocess.CompletedProcess[str]:
    out = subprocess.run(
        [sys.executable, "-m", "harness", *args],
        capture_output=True,
        text=True,
        cwd=work,
        env=_env(site, work),
        timeout=300,
    )
    if code is not None:
        assert out.returncode == code, f"harness {' '.join(args)} exited {out.returncode}:\n{out.stderr[-3000:]}"
    for broken in ("config file not found", "missing from this installation"):
        assert broken not in out.stderr, f"harness {' '.join(args)}:\n{out.stderr[-3000:]}"
    return out


def test_wheel_carries_configs_and_shipped_references(wheel_install):
    wheel, _ = wheel_install
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = sorted(p.relative_to(REPO / "configs").as_posix() for p in (REPO / "configs").rglob("*.yaml"))
    assert configs and {f"harness/configs/{c}" for c in configs} <= names
    references = [p for p in (REPO / "references").rglob("*") if p.is_file()]
    shipped = {f"harness/shipped_references/{p.relative_to(REPO / 'references').as_posix()}" for p in references}
    assert SHIPPED_MANIFEST in shipped and shipped <= names


def test_installed_copy_finds_its_configs_and_references(wheel_install, outside):
    _, site = wheel_install
    probe = (
        "import json, harness, adapters\n"
        "from harness.config import config_dir, config_file, load_config\n"
        "from harness.references import shipped_root\n"
        "print(json.dumps({'harness': harness.__file__, 'adapters': adapters.__file__, 'configs': str(config_dir()),\n"
        "  'references': str(shipped_root()), 'demo_ours': str(config_file('configs/demo/ours.yaml')),\n"
        "  'sources': {p: load_config(p, protocol='m3t-4fold')['meta']['sources']\n"
        "              for p in ('smoke', 'demo', 'benchmark')}}))"
    )
    found = json.loads(_python(site, outside, probe))
    installed = site / "harness"
    for key in ("harness", "adapters"):
        assert Path(found[key]).resolve().is_relative_to(site.resolve()), found[key]
    assert Path(found["configs"]) == installed / "configs"
    assert Path(found["references"]) == installed / "shipped_references"
    assert Path(found["demo_ours"]) == installed / "configs" / "demo" / "ours.yaml"
    for profile, sources in found["sources"].items():
        assert sources == [
            str(installed / "configs" / "protocols" / "m3t-4fold.yaml"),
            str(installed / "configs" / "profiles" / f"{profile}.yaml"),
        ]


def test_run_help_and_unknown_profile_from_outside(wheel_install, outside):
    _, site = wheel_install
    assert "--profile" in _harness(site, outside, "run", "--help").stdout
    err = _harness(site, outside, "run", "--detector", "ours", "--dataset", "m3t-synth", "--profile", "nosuch", code=2)
    assert "unknown profile 'nosuch'" in err.stderr and str(site / "harness" / "configs" / "profiles") in err.stderr
    assert all(p in err.stderr.split("available:")[1] for p in ("benchmark", "demo", "smoke"))


def test_run_and_report_with_shipped_references_from_outside(wheel_install, outside):
    _, site = wheel_install
    _harness(site, outside, "synth", "--size", "tiny", "--no-progress")
    assert (outside / "data" / "m3t-synth-tiny-seed0").is_dir()
    tiny = ["--set", "dataset.profile=tiny"]
    _harness(site, outside, "prepare", "--dataset", "m3t-synth", *tiny, "--no-progress")
    store = outside / "results"
    run = [
        *("run", "--detector", "ours", "--dataset", "m3t-synth", "--profile", "demo", "--folds", "P1"),
        *("--config", "configs/demo/ours.yaml", "--store", str(store), "--no-progress", *tiny),
    ]
    _harness(site, outside, *run, *[a for s in TINY_RUN for a in ("--set", s)])
    (config,) = store.glob("m3t-synth/ours/*/P1/seed0/config.yaml")
    sources = yaml.safe_load(config.read_text())["meta"]["sources"]
    installed = site / "harness" / "configs"
    assert str(installed / "profiles" / "demo.yaml") in sources
    assert str(installed / "demo" / "ours.yaml") in sources

    report_args = ("report", "--store", str(store), "--out", str(outside / "report"), "--reference-results", "shipped")
    report = _harness(site, outside, *report_args, code=None)
    # the shipped references were read: a tiny-set run is refused as other samples (the references are the small
    # set at the benchmark profile); a run on their samples would be compared with them
    if report.returncode == 0:
        assert "ref:" in "".join(p.read_text() for p in (outside / "report").rglob("*.md"))
    else:
        assert "reference results (m3t-synth" in report.stderr, report.stderr[-3000:]
        assert "trained and scored on other samples" in report.stderr and "profile tiny vs small" in report.stderr


def test_config_file_prefers_the_working_folder_then_the_installed_copy(tmp_path, monkeypatch):
    from harness.config import config_dir, config_file, load_config
    from harness.errors import ConfigError

    monkeypatch.chdir(tmp_path)
    own = tmp_path / "configs" / "demo" / "ours.yaml"
    own.parent.mkdir(parents=True)
    own.write_text("protocol: {epochs: 2}\n")
    assert config_file("configs/demo/ours.yaml") == Path("configs/demo/ours.yaml")
    assert load_config(files=["configs/demo/ours.yaml"])["protocol"]["epochs"] == 2
    own.unlink()
    assert config_file("configs/demo/ours.yaml") == config_dir() / "demo" / "ours.yaml"
    assert config_file("configs/demo/nosuch.yaml") == Path("configs/demo/nosuch.yaml")
    assert config_file("ours.yaml") == Path("ours.yaml")
    with pytest.raises(ConfigError, match="configs/demo/nosuch.yaml"):
        load_config(files=["configs/demo/nosuch.yaml"])
