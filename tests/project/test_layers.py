"""The layers the README draws are the code's: import-linter's contract (pyproject.toml) holds on the tree,
and breaks when a lower layer imports an upper one."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("twin", "controllers", "viz", "models")


def lint_imports(folder: Path) -> subprocess.CompletedProcess:
    """import-linter on the packages found in `folder`, with the contract in its pyproject.toml."""
    return subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command as c; "
                           "sys.exit(c())", "--config", str(folder / "pyproject.toml"), "--no-cache"],
                          capture_output=True, text=True, cwd=folder, env={"PYTHONPATH": str(folder), "PATH": ""},
                          timeout=300)


def copy_tree(dest: Path) -> Path:
    for name in PACKAGES:
        shutil.copytree(ROOT / name, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", dest / "pyproject.toml")
    return dest


def test_the_layers_hold():
    r = lint_imports(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 kept, 0 broken" in r.stdout


def test_an_upward_import_breaks_the_contract(tmp_path):
    tree = copy_tree(tmp_path)
    spec = tree / "twin" / "device" / "spec.py"  # the bottom of the device layers: it may not reach up
    spec.write_text(spec.read_text() + "\n\ndef _upward():\n    from twin.sim import gate  # noqa: F401\n")
    r = lint_imports(tree)
    assert r.returncode != 0
    assert "BROKEN" in r.stdout and "twin.device.spec -> twin.sim.gate" in r.stdout, r.stdout


def test_siblings_of_one_layer_stay_apart(tmp_path):
    tree = copy_tree(tmp_path)
    target = tree / "twin" / "morphpatch" / "sampling.py"  # the approximation never imports the link
    target.write_text(target.read_text() + "\n\ndef _sideways():\n    from twin.link import protocol  # noqa: F401\n")
    r = lint_imports(tree)
    assert r.returncode != 0 and "twin.morphpatch.sampling -> twin.link.protocol" in r.stdout, r.stdout
