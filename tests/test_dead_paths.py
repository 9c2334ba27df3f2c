"""Every path the project's docs, docstrings and comments name is one the repository holds.

A path is a relative file name ending in a known extension, or a folder ending in /, whose first
folder is one of the repository's own (server/..., estimation/forecast.py, decisions/): a name
under a folder the repository does not have (mujoco/..., a package's own files, the data root's
frames/) is someone else's and is not checked here. It resolves from the repository's root, from the
naming file's folder, or as the tail of a path the repository holds (estimation/forecast.py is
server/estimation/forecast.py); jitdyn/... is the installed package's name for the same files.
Read: Markdown whole (links' URLs aside), Python's comments and docstrings, and the comments of
C++, proto, TOML, YAML, shell and Dockerfiles. Test data inside code strings is not a reference.
"""

from __future__ import annotations

import ast
import io
import re
import subprocess
import tokenize
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXTENSIONS = "py|pyi|md|proto|cc|h|toml|yaml|yml|json|sh|txt|cfg|ini|png|gif|sql|xml|csv"
# A run of path segments (a/b/c.ext or a/b/), not inside a longer word, URL or absolute path.
PATH = re.compile(
    rf"(?<![\w./:@~$<>-])((?:\.\.?/)*(?:[\w.-]+/)+(?:[\w-][\w.-]*\.(?:{EXTENSIONS})\b(?![\w/-])|(?![\w.-])))"
)
URL = re.compile(r"\w+://\S+")


@cache
def held() -> tuple[frozenset[str], frozenset[str]]:
    """The repository's files and folders (relative, POSIX)."""
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    )
    files = frozenset(listed.stdout.split())
    folders = {str(parent) for f in files for parent in Path(f).parents if str(parent) != "."}
    return files, frozenset(folders)


def folder_names() -> frozenset[str]:
    return frozenset(Path(f).name for f in held()[1]) | {"jitdyn"}


def exists(reference: str, naming: str) -> bool:
    files, folders = held()
    bare = reference.rstrip("/")
    if bare.startswith("jitdyn/"):  # the installed package maps the top-level folders into it
        bare = bare.removeprefix("jitdyn/")
        bare = bare.removeprefix("src/")
    candidates = {bare, (Path(naming).parent / bare).as_posix()}
    for candidate in candidates:
        try:
            normal = (ROOT / candidate).resolve().relative_to(ROOT.resolve()).as_posix()
        except ValueError:  # above the repository
            continue
        if normal in files or normal in folders:
            return True
    tail = "/" + bare.lstrip("./")
    return any(f.endswith(tail) for f in files) or any(f.endswith(tail) for f in folders)


def texts(name: str, source: str) -> list[tuple[int, str]]:
    """(line, text) of the parts of a file that are prose: see the module docstring."""
    if name.endswith(".md"):
        return list(enumerate(source.splitlines(), 1))
    if name.endswith(".py"):
        return _python_prose(source)
    if name.endswith((".cc", ".h", ".proto", ".pyi")):
        marker = "#" if name.endswith(".pyi") else "//"
        return [
            (n, line.split(marker, 1)[1]) for n, line in enumerate(source.splitlines(), 1) if marker in line
        ]
    return [(n, line.split("#", 1)[1]) for n, line in enumerate(source.splitlines(), 1) if "#" in line]


def _python_prose(source: str) -> list[tuple[int, str]]:
    prose = [
        (token.start[0], token.string)
        for token in tokenize.generate_tokens(io.StringIO(source).readline)
        if token.type == tokenize.COMMENT
    ]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            first = node.body[0] if node.body else None
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                prose += [(first.lineno + i, line) for i, line in enumerate(first.value.value.splitlines())]
    return prose


def _scanned(name: str) -> bool:
    if name.startswith("src/jitdyn/v1/"):  # generated
        return False
    return bool(re.search(r"\.(py|pyi|md|proto|cc|h|toml|ya?ml|sh|cfg)$", name)) or name.endswith(
        ("Dockerfile", ".ci/run")
    )


def dead_paths() -> list[str]:
    own = folder_names()
    dead = []
    for name in sorted(held()[0]):
        if not _scanned(name):
            continue
        source = (ROOT / name).read_text(encoding="utf-8", errors="replace")
        for line, text in texts(name, source):
            for match in PATH.finditer(URL.sub(" ", text)):
                reference = match.group(1)
                if reference.startswith("..."):  # an ellipsis, not a folder
                    continue
                first = next(part for part in reference.split("/") if part not in ("", ".", ".."))
                if (first in own or reference.startswith(".")) and not exists(reference, name):
                    dead.append(f"{name}:{line}: {reference}")
    return dead


def test_every_path_the_docs_and_comments_name_is_in_the_repository() -> None:
    dead = dead_paths()
    assert not dead, f"{len(dead)} paths named that the repository does not hold:\n" + "\n".join(dead)


def test_the_check_finds_a_dead_path_and_passes_a_living_one() -> None:
    """The scanner itself: a path the repository holds, in its short and installed forms, passes; a
    misspelt one, and a folder that is not there, are found."""
    assert exists("server/runtime/session.py", "README.md")
    assert exists("estimation/forecast.py", "server/runtime/session.py")
    assert exists("jitdyn/server/transport/app.py", "scripts/wheel_smoke.py")
    assert exists("../runtime/session.py", "server/estimation/ukf.py")
    assert exists("docs/decisions/", "README.md")
    assert not exists(
        "docs/decisions/0121-refusals-through-haproxy.md", "server/transport/dynamics_service.py"
    )
    assert not exists("server/nowhere/", "README.md")
    found = [m.group(1) for m in PATH.finditer("see estimation/forecast.py, docs/decisions/ and x.py or a/b")]
    assert found == ["estimation/forecast.py", "docs/decisions/"], found
    prose = _python_prose('"""Doc: docs/a.md."""\nx = "parts/arm.xml"  # tests/b.py\n')
    assert [text for _, text in prose] == ["# tests/b.py", "Doc: docs/a.md."]
