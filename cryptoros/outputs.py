"""Writing a file an operator named on the command line (``--json``, ``--out``, a plot).

An operator who names ``sim-out/run.json`` expects ``sim-out/`` to be made, as
``cryptoros demo --json`` does, so the directories on the way are created. A write that
still fails (no permission, a full disk, a file where a directory should be) is one
:class:`click.ClickException` line naming the file, not a traceback: the run before it
may have taken minutes, and its figures are already on stdout.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import click


@contextmanager
def writing(path: str | os.PathLike[str]) -> Iterator[Path]:
    """``path`` as a :class:`Path` whose parent directories exist; an :class:`OSError`
    raised in the block (making them, or the caller's write) becomes one line. Keep the
    block to the write itself, so the line names the right file."""
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        yield target
    except OSError as exc:
        # the file in the way may be a parent ("File exists" alone would not say which)
        where = f" ({exc.filename})" if exc.filename and Path(exc.filename) != target else ""
        raise click.ClickException(f"cannot write {target}: {exc.strerror or exc}{where}") from None


def write_output(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` to ``path`` (see :func:`writing`); the path written."""
    with writing(path) as target:
        target.write_text(text)
    return target


__all__ = ["write_output", "writing"]
