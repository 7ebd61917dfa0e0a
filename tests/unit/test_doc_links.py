"""Every file the repository's Markdown names exists: relative links (``[x](docs/a.md)``)
and repository paths in code spans (`` `cryptoros/policy/ros1.py` ``). A module moved
into a package, or a link to a file outside the repository, leaves a newcomer a dead
end."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SKIP = {".venv", ".git", "node_modules"}
LINK = re.compile(r"\]\(([^)\s]+)\)")
#: a path inside one of the repository's top directories, or one leaving the file's directory
SPAN = re.compile(r"`((?:\.\./|(?:cryptoros|interceptor|authz_server|certs|tests|docs|scripts)/)[\w./-]+"
                  r"\.(?:py|md|toml|yaml|sh|json))`")


def _markdown() -> list[Path]:
    return [p for p in REPO.rglob("*.md")
            if not any(part in SKIP or part.endswith(".egg-info") for part in p.relative_to(REPO).parts)]


def _named(md: Path) -> list[tuple[int, str, list[Path]]]:
    """(line, as written, where it may be) for each file ``md`` names."""
    text = md.read_text(errors="replace")
    found = []
    for m in LINK.finditer(text):
        target = m.group(1).split("#")[0]
        if target and not re.match(r"^[a-z][a-z0-9+.-]*:", target):  # not http:, mailto: ...
            found.append((text.count("\n", 0, m.start()) + 1, m.group(1), [md.parent / target]))
    for m in SPAN.finditer(text):
        path = m.group(1)
        # a repository path is written from the top; a relative one from the file's directory
        found.append((text.count("\n", 0, m.start()) + 1, path, [md.parent / path] + ([] if path.startswith("..") else [REPO / path])))
    return found


def test_every_file_the_markdown_names_exists():
    dead = [f"{md.relative_to(REPO)}:{line}: {written}"
            for md in _markdown() for line, written, where in _named(md)
            if not any(p.exists() and REPO in p.resolve().parents for p in where)]
    assert not dead, "dead links:\n" + "\n".join(dead)
