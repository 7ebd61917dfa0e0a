"""The files of a PKI directory (:mod:`certs.pki`): written whole or not at all, under
the directory's lock, and the CA replaced so that a stop anywhere leaves the old CA or
the new one.

Every file is written to a temporary file in its target directory and then moved into
place (:class:`FileSet`, :func:`write_file`); nothing is overwritten without
``force``. Every change holds the lock ``.lock`` (:func:`pki_lock`); taking it removes
temporary files of our own pattern (``.<file>.<8 chars>.tmp``) that a killed run left
behind. ``init`` stages the whole CA in ``.init.new/``, renames it to ``.init.ready/``
(the point of no return) and moves the files into place (:func:`replace_ca`); the
replaced ones are kept as ``*.old``, and a move interrupted after that point is finished
by the next :func:`finish_init`. Failures raise :class:`~cryptoros.errors.PKIError`
naming the real file.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from cryptoros.errors import PKIError
from cryptoros.files import sync

#: what tempfile.mkstemp makes for FileSet: ".<final name>.<8 random chars>.tmp"
_TEMP_RE = re.compile(r"^\.[^/]+\.[a-z0-9_]{8}\.tmp$")
#: temp files older than this process cannot be ours in flight: a killed run's leftovers
_STARTED = time.time()
_INIT_FILES = ("ca.crt", "private/ca.key", "index.json", "crl.pem")  # what init replaces, in that order


class FileSet:
    """Stage several files as temporaries in their target directories, then move them
    all into place. Nothing existing is replaced without ``force``; if one move fails
    the files this set already created are removed again."""

    def __init__(self, *, force: bool) -> None:
        self.force = force
        self.staged: list[tuple[Path, Path]] = []  # (tmp, final)

    def check(self, final: Path) -> None:
        if not self.force and (final.exists() or final.is_symlink()):
            raise PKIError(f"{final} exists: use --force to overwrite")

    def add(self, final: Path, data: bytes, mode: int) -> None:
        self.check(final)
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=final.parent, prefix=f".{final.name}.", suffix=".tmp")
        except OSError as err:
            raise _write_error(final, err) from err
        try:
            os.fchmod(fd, mode)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        except BaseException as err:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            if isinstance(err, OSError):
                raise _write_error(final, err) from err
            raise
        self.staged.append((Path(tmp), final))

    def commit(self) -> None:
        created: list[Path] = []
        try:
            for tmp, final in self.staged:
                if self.force:
                    _replace(tmp, final)
                else:
                    try:
                        os.link(tmp, final)  # atomic, and refuses to clobber
                    except FileExistsError as err:
                        raise PKIError(f"{final} exists: use --force to overwrite") from err
                    except OSError:
                        # no hard links on this file system: check, then rename
                        if final.exists() or final.is_symlink():
                            raise PKIError(f"{final} exists: use --force to overwrite") from None
                        _replace(tmp, final)
                    else:
                        os.unlink(tmp)
                created.append(final)
        except BaseException:
            if not self.force:
                for path in created:
                    with contextlib.suppress(OSError):
                        path.unlink()
            raise
        finally:
            self.discard()

    def discard(self) -> None:
        for tmp, _ in self.staged:
            with contextlib.suppress(OSError):
                tmp.unlink()
        self.staged = []

    def __enter__(self) -> FileSet:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()


def _write_error(final: Path, err: OSError) -> PKIError:
    """An OSError while writing ``final`` (perhaps through its temporary file), as a
    PKIError naming ``final``: the temporary name means nothing to the user."""
    return PKIError(f"cannot write {final}: {err.strerror or err}")


def _replace(tmp: Path, final: Path) -> None:
    try:
        os.replace(tmp, final)
    except OSError as err:
        raise _write_error(final, err) from err


def _remove_stale_temps(directory: Path) -> list[Path]:
    """Remove the temporary files a killed run left in the PKI directory: only regular
    files matching :data:`_TEMP_RE`, directly in the directory or its subdirectories of
    the layout, and last changed before this process started (every live writer holds
    the lock we hold, so nothing in flight is touched). Returns what was removed."""
    removed = []
    for sub in (directory, directory / "private", directory / "issued", directory / "csr"):
        try:
            entries = list(os.scandir(sub))
        except OSError:
            continue
        for entry in entries:
            if not _TEMP_RE.match(entry.name):
                continue
            try:
                st = entry.stat(follow_symlinks=False)
                if stat.S_ISREG(st.st_mode) and st.st_mtime < _STARTED:
                    os.unlink(entry.path)
                    removed.append(Path(entry.path))
            except OSError:
                continue  # gone already, or not ours to remove
    return removed


@contextlib.contextmanager
def pki_lock(directory: Path) -> Iterator[None]:
    """Hold the PKI's exclusive lock (``.lock``), after removing stale temporary files."""
    fd = os.open(directory / ".lock", os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        _remove_stale_temps(directory)
        yield
    finally:
        os.close(fd)


INIT_STAGING = ".init.new"  # a CA being written: removed by the next init
INIT_READY = ".init.ready"  # a CA complete on disk: moved into place by the next open or init


def refuse_existing_ca(directory: Path) -> None:
    for rel in ("ca.crt", "private/ca.key", "index.json"):
        if (directory / rel).exists():
            raise PKIError(f"{directory / rel} exists: use --force to overwrite")


def replace_ca(directory: Path, files: dict[str, tuple[bytes, int]]) -> None:
    """Replace the CA's files so that a stop anywhere leaves the old CA or the new one
    (under the caller's lock). The new files are written whole into ``.init.new/``;
    the current ones are linked to ``*.old``; renaming the staging directory to
    ``.init.ready/`` commits; :func:`_finish_init` then moves the files into place."""
    staging = directory / INIT_STAGING
    shutil.rmtree(staging, ignore_errors=True)  # an init stopped before committing
    (staging / "private").mkdir(parents=True, mode=0o700)
    for rel, (data, mode) in files.items():
        write_file(staging / rel, data, mode=mode)
    sync(staging / "private")
    sync(staging)
    for rel in _INIT_FILES:
        live = directory / rel
        if live.is_file() and not live.is_symlink():
            old = live.with_name(live.name + ".old")
            with contextlib.suppress(FileNotFoundError):
                old.unlink()
            try:
                os.link(live, old)  # the same inode: a stop now loses nothing
            except OSError:
                shutil.copy2(live, old)  # no hard links on this file system
    os.rename(staging, directory / INIT_READY)  # the point of no return
    sync(directory)
    finish_init(directory)


def finish_init(directory: Path) -> None:
    """Move a committed CA (``.init.ready/``) into place (under the caller's lock)."""
    ready = directory / INIT_READY
    if not ready.is_dir():
        return
    for rel in _INIT_FILES:
        staged = ready / rel
        if staged.exists():  # absent: moved already, by the init that stopped
            _replace(staged, directory / rel)
    sync(directory)
    sync(directory / "private")
    shutil.rmtree(ready)



def write_file(path: str | os.PathLike, data: bytes, *, mode: int = 0o644, force: bool = False) -> Path:
    path = Path(path)
    with FileSet(force=force) as fs:
        fs.add(path, data, mode)
    return path


__all__ = ["INIT_READY", "FileSet", "finish_init", "pki_lock", "refuse_existing_ca", "replace_ca", "write_file"]
