"""The layers the README draws are the code's: import-linter's contract (pyproject.toml) holds on the tree,
and breaks when a lower layer imports an upper one."""

import ast
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


COMMAND_LINES = 80  # issue 39: a command parses its options, calls its concern's function and prints, in ~80 lines


def test_a_command_parses_calls_and_prints():
    """Every command module within COMMAND_LINES (what a command once did by hand lives in its concern's package,
    where the layers check it), and the shared options module declares options only: what they open (the profile's
    folders, the device's link and session) lives below the commands (twin.formats.profile.chosen_profile,
    twin.hil.device_gains.device_session), not in it."""
    shared = ("__init__.py", "options.py", "interrupts.py")
    long = {p.name: n for p in (ROOT / "twin/commands").glob("*.py")
            if p.name not in shared and (n := len(p.read_text().splitlines())) > COMMAND_LINES}
    assert not long, f"command modules over {COMMAND_LINES} lines: {long}"
    tree = ast.parse((ROOT / "twin/commands/options.py").read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    opening = sorted(m for m in imported if m.startswith(("twin.link", "twin.hil", "twin.sim", "twin.device.profile")))
    assert not opening, f"twin/commands/options.py opens what belongs below the commands: {opening}"
