"""The project installs like any other package: a wheel (and an sdist) built from the tree, installed into a
fresh virtual environment, runs its commands from an empty folder, its data found inside the package."""

import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SOURCES = ("twin", "controllers", "viz", "models", "pyproject.toml", "README.md")


def run(cmd, **kw) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600, **kw)
    assert r.returncode == 0, f"{cmd}: {r.stdout[-2000:]}{r.stderr[-2000:]}"
    return r


def source_copy(dest: Path) -> Path:
    """The tree's sources in a folder of their own (a build writes build/ and *.egg-info beside them)."""
    for name in SOURCES:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy(src, dest / name)
    return dest


def fresh_env(folder: Path) -> Path:
    """A new virtual environment whose only extra path is this one's site-packages (the dependencies, not
    the project: an editable install's finder there is not loaded from a path entry); its python."""
    venv.create(folder, with_pip=False)
    py = folder / "bin" / "python"
    purelib = run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip()
    (Path(purelib) / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return py


def install(artifact: Path, env: Path) -> Path:
    """`pip install --no-deps ARTIFACT` into env; its `vrscroll` script."""
    run([sys.executable, "-m", "pip", "--python", env, "install", "-q", "--no-deps", artifact])
    return env.parent / "vrscroll"


def user_env(tmp_path: Path) -> dict:
    return {**os.environ, "VRSCROLL_CACHE": str(tmp_path / "cache"), "VRSCROLL_DEVICES": str(tmp_path / "devices"),
            "PYTHONPATH": ""}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = source_copy(tmp_path_factory.mktemp("src"))
    out = tmp_path_factory.mktemp("dist")
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", out, src])
    return next(out.glob("vrscroll_twin-*.whl"))


def test_wheel_carries_the_data_and_the_firmware(wheel):
    import zipfile

    names = set(zipfile.ZipFile(wheel).namelist())
    for needed in ("models/vrscroll/spec.toml", "models/vrscroll/vrscroll.xml", "models/shapes/shapes.toml",
                   "models/perception/perception.toml", "controllers/firmware/vrs_core.c", "twin/cli.py"):
        assert needed in names, needed


@pytest.mark.slow  # suite time: the default suite stays under 10 min on 2 cores (run with -m slow)
def test_installed_wheel_runs_from_an_empty_folder(wheel, tmp_path):
    vrscroll = install(wheel, fresh_env(tmp_path / "env"))
    empty = tmp_path / "empty"
    empty.mkdir()
    env = user_env(tmp_path)
    where = run([tmp_path / "env" / "bin" / "python", "-c", "import models, twin; print(models.__file__, twin.__file__)"],
                cwd=empty, env=env).stdout
    assert str(ROOT) not in where and str(tmp_path / "env") in where  # the installed copy, not the tree
    r = run([vrscroll, "approximate", "--shape", "cube"], cwd=empty, env=env)
    assert '"msd_mm"' in r.stdout
    run([vrscroll, "model", "--check"], cwd=empty, env=env)
    r = run([vrscroll, "simulate", "10", "0", "0", "0", "0", "-10"], cwd=empty, env=env)  # builds the C core
    assert "settle" in r.stdout


@pytest.mark.slow
def test_installed_wheel_and_sdist_run_the_demo(wheel, tmp_path):
    src = source_copy(tmp_path / "src")
    dist = tmp_path / "dist"  # the sdist through the backend pip uses
    run([sys.executable, "-c", f"from setuptools import build_meta as b; print(b.build_sdist({str(dist)!r}))"], cwd=src)
    sdist = next(dist.glob("*.tar.gz"))
    with tarfile.open(sdist) as t:
        assert any(n.endswith("models/shapes/shapes.toml") for n in t.getnames())
    for artifact, name in ((wheel, "wheel"), (sdist, "sdist")):
        vrscroll = install(artifact, fresh_env(tmp_path / f"env-{name}"))
        empty = tmp_path / f"empty-{name}"
        empty.mkdir()
        run([vrscroll, "demo"], cwd=empty, env=user_env(tmp_path))
        assert (empty / "demo.png").stat().st_size > 10_000
