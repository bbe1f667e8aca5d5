"""Every name the prose gives for the code is one that is there: dotted names (`twin.sim.response.step_metrics`)
in docs/, the README and the docstrings and comments of the code resolve, and every repository path they give
exists. A module renamed without its mentions fails here."""

import importlib
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOTTED = re.compile(r"\b((?:twin|controllers|viz)\.[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)")
PATH = re.compile(r"\b((?:twin|controllers|viz|tests|benchmarks|docs|models|clients|results)/[\w/.\-]*"
                  r"\.(?:py|md|toml|xml|c|h|ino|json|csv|cs|ini))\b")
FILE_SUFFIX = re.compile(r"\.(py|md|toml|xml|json|csv|c|h|ino|ini|png)$")
CODE = ("twin", "controllers", "viz", "benchmarks", "tests")


def prose_files() -> list[Path]:
    return ([*sorted((ROOT / "docs").glob("*.md")), ROOT / "README.md", ROOT / ".ci" / "run", ROOT / "pyproject.toml"]
            + [p for d in CODE for p in sorted((ROOT / d).rglob("*.py"))])


def prose(path: Path):
    """The text a reader reads as prose: a whole doc, or a module's comments and docstrings (not its code, where
    a variable named twin has methods of its own)."""
    text = path.read_text()
    if path.suffix != ".py":
        yield text
        return
    previous = tokenize.NEWLINE
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT or (tok.type == tokenize.STRING and previous in (
                tokenize.NEWLINE, tokenize.NL, tokenize.INDENT, tokenize.DEDENT)):
            yield tok.string
        if tok.type != tokenize.COMMENT:
            previous = tok.type


def resolves(name: str) -> bool:
    """Whether the longest importable prefix of `name` has the rest as attributes."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def mentions():
    for path in prose_files():
        for text in prose(path):
            for m in DOTTED.finditer(text):
                if not FILE_SUFFIX.search(m.group(1)):
                    yield "name", path, m.group(1)
            for m in PATH.finditer(text):
                yield "path", path, m.group(1)


def test_every_name_and_path_in_the_prose_is_there():
    stale = sorted({f"{path.relative_to(ROOT)}: {name}" for kind, path, name in mentions()
                    if not (resolves(name) if kind == "name" else (ROOT / name).exists())})
    assert not stale, "names in the prose that the code does not have:\n" + "\n".join(stale)


@pytest.mark.parametrize("name, there", [("twin.sim.response.step_metrics", True),
                                         ("twin.simulation.hinge_metrics", False),
                                         ("twin.sim.response.no_such_function", False)])
def test_the_check_tells_a_stale_name(name, there):
    assert resolves(name) is there
