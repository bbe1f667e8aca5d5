"""Benchmarks import the package, never a test module (issue 39): what a benchmark shares with the tests (the drawn
plant, the shape corpus, the judges) lives in the package, so a benchmark runs with only the project on its path.
Each benchmark's imports are read (not run) and each is checked against the modules the tests folder holds."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def modules_of_tests(root: Path = ROOT / "tests") -> set[str]:
    """Every name a test-folder module can be imported by, with the folder or one of its subfolders on the path."""
    names = set()
    for path in root.rglob("*.py"):
        rel = path.relative_to(root).with_suffix("")
        names |= {".".join(rel.parts[i:]) for i in range(len(rel.parts))}
    return names | {p.name for p in root.iterdir() if p.is_dir()}


def imported(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
    return names


def test_no_benchmark_imports_a_test_module():
    tests = modules_of_tests()
    assert {"cli", "conftest", "tuning.test_tuning_hil", "test_tuning_hil", "tuning"} <= tests  # the check sees them
    found = {str(p.relative_to(ROOT)): sorted(imported(p) & tests) for p in sorted((ROOT / "benchmarks").glob("*.py"))}
    assert found and not any(found.values()), {k: v for k, v in found.items() if v}
    for path in (ROOT / "benchmarks").glob("*.py"):  # nor put the tests folder on their path
        text = path.read_text()
        assert '/ "tests")' not in text and "$PWD/tests" not in text, path
