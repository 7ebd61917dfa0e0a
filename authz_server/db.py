"""Database engine, schema migrations and sessions for the registry.

Any SQLAlchemy URL works; SQLite is the embedded default (WAL mode, foreign keys on,
a busy timeout so the daemon and the admin CLI can share the file) and PostgreSQL is
the multi-replica choice (``postgresql+psycopg://``).

The schema is Alembic's: :func:`open_registry` upgrades an empty or older database to
the newest revision, and refuses a database that is not a registry or that is newer
than this code. A new SQLite registry is built whole in a file beside it and renamed
into place, so an interrupted first upgrade leaves no file or a complete one. A path
that is not an SQLite file (a directory, a device, a text file) is refused before
anything touches it; only a registry is made owner-only.
"""

from __future__ import annotations

import logging
import os
import secrets
import stat
from pathlib import Path

from typing import TYPE_CHECKING

from sqlalchemy import Engine, create_engine, event, inspect, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, NoSuchModuleError, OperationalError, SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from cryptoros.errors import ConfigError
from cryptoros.files import sync

if TYPE_CHECKING:
    from alembic.config import Config

# Alembic is imported only when a migration has to run or be inspected: the admin CLI
# starts faster, and the daemon's usual start (schema already at head) needs none.

log = logging.getLogger(__name__)

DEFAULT_DB_URL = "sqlite:///./cryptoros-authz.db"
MIGRATIONS = "authz_server:migrations"
#: the newest migration; a test checks it equals Alembic's head
KNOWN_HEAD = "0005"


def _alembic_config(url: str) -> Config:
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", MIGRATIONS)
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


def head_revision() -> str:
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(_alembic_config("sqlite://")).get_current_head()
    assert head is not None
    return head


def _sqlite_path(url: str) -> Path | None:
    """The file of an SQLite URL; None for another backend, memory, or an unreadable URL
    (:func:`make_engine` says what is wrong with it)."""
    try:
        u = make_url(url)
    except ArgumentError:
        return None
    if u.get_backend_name() != "sqlite" or not u.database or u.database == ":memory:":
        return None
    return Path(u.database)


#: the first 16 bytes of every SQLite database file
SQLITE_HEADER = b"SQLite format 3\x00"


def _check_sqlite_file(path: Path, *, create: bool) -> None:
    """Refuse, before anything opens or changes it, a path that cannot be a registry: a
    missing directory, a missing file (unless ``create``), a directory, a device or pipe,
    a file that is not SQLite. (CLI audit: a --db naming a text file or a directory had
    its mode changed before SQLite failed on it.) An empty file is an empty database."""
    if not path.parent.is_dir():
        raise ConfigError(f"database directory does not exist: {path.parent}")
    try:
        st = path.stat()
    except FileNotFoundError:
        if create:
            return
        raise ConfigError(f"database not found: {path} (create it with 'cryptoros-authz db upgrade')") from None
    except OSError as exc:
        raise ConfigError(f"cannot use the database {path}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"{path} is a directory, not a registry database file (name the file in it, "
                          f"e.g. sqlite:///{path / 'registry.db'})")
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"{path} is not a regular file, so not a registry database; it was left unchanged")
    if st.st_size and _header(path) != SQLITE_HEADER:
        raise ConfigError(f"{path} is not an SQLite database, so not a registry (a wrong --db?); "
                          "it was left unchanged")


def _header(path: Path) -> bytes:
    try:
        with path.open("rb") as f:
            return f.read(len(SQLITE_HEADER))
    except OSError as exc:
        raise ConfigError(f"cannot read the database {path}: {exc.strerror or exc}") from None


def make_engine(url: str, *, create: bool = False, pool_size: int = 8) -> Engine:
    """An engine for ``url``. A missing SQLite file is an error unless ``create``; a path
    that is not an SQLite file is an error, and left unchanged."""
    try:
        parsed = make_url(url)
    except ArgumentError as exc:
        raise ConfigError(f"invalid database URL {url!r}: {exc}") from exc
    path = _sqlite_path(url)
    if path is not None:
        _check_sqlite_file(path, create=create)
        if create and not path.exists():
            _create_private(path)
    kwargs: dict = {}
    if parsed.get_backend_name() == "sqlite":
        kwargs["connect_args"] = {"timeout": 30, "check_same_thread": False}
    else:
        kwargs.update(pool_size=pool_size, max_overflow=pool_size, pool_pre_ping=True)
    try:
        engine = create_engine(url, **kwargs)
    except (ArgumentError, NoSuchModuleError, ImportError) as exc:
        raise ConfigError(f"cannot use database URL {parsed.render_as_string(hide_password=True)}: {exc}") from exc
    if parsed.get_backend_name() == "sqlite":
        event.listen(engine, "connect", _sqlite_pragmas)
    return engine


def _create_new_sqlite(url: str, path: Path) -> None:
    """Build a new SQLite registry whole beside ``path`` and rename it into place.

    SQLite's driver commits each CREATE TABLE on its own, so a first ``db upgrade``
    killed mid-way left a file with tables and no schema revision, refused by every
    command after (CLI audit). Built in a temporary file, an interruption leaves no
    registry (a stray ``.NAME.*.new`` at worst), and a failure cleans up."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.new")
    _create_private(tmp)
    try:
        engine = make_engine(make_url(url).set(database=str(tmp)).render_as_string(hide_password=False))
        try:
            upgrade(engine)
            with engine.connect() as conn:  # all of it in the file itself: only that is renamed
                conn.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            engine.dispose()
        sync(tmp)
        _install(tmp, path)
        sync(path.parent)
    except SQLAlchemyError as exc:
        raise ConfigError(f"cannot create the registry {path}: {_first_line(exc)}") from exc
    except OSError as exc:
        raise ConfigError(f"cannot create the registry {path}: {exc.strerror or exc}") from None
    finally:
        for file in (tmp, tmp.with_name(tmp.name + "-wal"), tmp.with_name(tmp.name + "-shm")):
            file.unlink(missing_ok=True)


def _install(tmp: Path, path: Path) -> None:
    """``tmp`` becomes ``path``: over an empty file (made by hand or by an older version),
    never over a registry another tool created meanwhile (that one is kept and used)."""
    if path.exists():
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        pass
    except OSError:  # a file system without hard links: a rename, which a race could overwrite
        os.replace(tmp, path)


def _create_private(path: Path) -> None:
    """An empty SQLite file only its owner reads (SQLite gives its -wal and -shm files the
    same mode): the registry holds the token-signing key, and a file made with the
    umask's 0644 let every local user read it (CLI audit)."""
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConfigError(f"cannot create the database {path}: {exc.strerror or exc}") from None


def _tighten(path: Path) -> None:
    """An existing registry file (and its -wal and -shm files) that other local users may
    read or write is made owner-only, with a warning: a file made 0644 by hand, by a
    restore or by an older version still held the token-signing key."""
    for file in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")):
        try:
            mode = file.stat().st_mode & 0o777
            if mode & 0o077:
                file.chmod(mode & 0o700)
                log.warning("%s was readable or writable by other users (mode %o): made %o, as a registry "
                            "holding the token-signing key must be", file, mode, mode & 0o700)
        except FileNotFoundError:
            continue
        except OSError as exc:
            log.warning("%s is readable or writable by other users and could not be made owner-only: %s",
                        file, exc.strerror or exc)


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def current_revision(engine: Engine) -> str | None:
    with engine.connect() as conn:
        return _revision(conn)


def _revision(conn) -> str | None:
    if not inspect(conn).has_table("alembic_version"):
        return None
    rows = conn.execute(text("SELECT version_num FROM alembic_version")).scalars().all()
    if len(rows) > 1:
        raise ConfigError(f"registry has several schema heads: {', '.join(rows)}")
    return rows[0] if rows else None


def upgrade(engine: Engine, revision: str = "head") -> str:
    """Run the Alembic migrations up to ``revision`` on ``engine``; return the result."""
    from alembic import command

    cfg = _alembic_config(engine.url.render_as_string(hide_password=False))
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, revision)
    rev = current_revision(engine)
    assert rev is not None
    return rev


def open_registry(url: str, *, create: bool = False) -> Engine:
    """Open the registry at ``url``: connect, check it is ours, migrate to head.

    Raises :class:`ConfigError` with a one-line reason on every failure.
    """
    path = _sqlite_path(url)
    if path is not None:
        _check_sqlite_file(path, create=create)
        if not path.exists() or path.stat().st_size == 0:
            _create_new_sqlite(url, path)
    engine = make_engine(url, create=create)
    shown = engine.url.render_as_string(hide_password=True)
    try:
        with engine.connect() as conn:
            tables = set(inspect(conn).get_table_names())
            rev = _revision(conn)
    except OperationalError as exc:
        engine.dispose()
        raise ConfigError(f"cannot connect to the database {shown}: {_first_line(exc)}") from exc
    except SQLAlchemyError as exc:
        engine.dispose()
        raise ConfigError(f"database error on {shown}: {_first_line(exc)}") from exc
    if rev is None and tables - {"alembic_version"}:
        engine.dispose()
        raise ConfigError(_not_a_registry(shown, path, tables))
    if path is not None:
        _tighten(path)
    if rev == KNOWN_HEAD:
        return engine
    from alembic.script import ScriptDirectory
    from alembic.util import CommandError

    script = ScriptDirectory.from_config(_alembic_config(shown))
    if rev is not None:
        try:
            script.get_revision(rev)
        except CommandError:
            engine.dispose()
            raise ConfigError(f"{shown} is at schema revision {rev}, unknown to this cryptoros-authz "
                              "(a newer version made it?)") from None
    if rev != script.get_current_head():
        try:
            upgrade(engine)
        except SQLAlchemyError as exc:
            engine.dispose()
            raise ConfigError(f"cannot migrate {shown}: {_first_line(exc)}") from exc
    return engine


def _not_a_registry(shown: str, path: Path | None, tables: set[str]) -> str:
    """Why a database with tables and no schema revision is refused, and what to do.

    Our tables beside an empty alembic_version are a first upgrade that was stopped (by
    an older version, which built a new registry in place): nothing in it was ever used."""
    if "alembic_version" in tables and "manager" in tables:
        where = f"remove {path}" if path is not None else "empty the database"
        return (f"{shown} holds registry tables but no schema revision: its first 'db upgrade' was "
                f"interrupted; if it holds nothing you need, {where} and run 'cryptoros-authz db upgrade'")
    return f"{shown} holds tables but is not a cryptoros-authz registry"


def _first_line(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None)
    text = str(orig if orig is not None else exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


def shown_db(url: str) -> str:
    """A database URL as logs and errors show it: the password masked (SQLAlchemy's own
    rendering, as :func:`make_engine`'s errors show it)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return "(an unreadable database URL)"
