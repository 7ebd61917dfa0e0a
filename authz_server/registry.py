"""Operations over the registry: the one place that reads and writes its tables.

Why one long module: it is the one place that writes the tables, and each write and its
change row (below) share one transaction and one lock; what is pure (a policy's rows,
proposals, SROS2, drafts) lives in the modules beside it.

Both the admin CLI and the daemon go through :class:`Registry`. Every method runs in
its own transaction and validates all of its input before it writes anything, so a
refused operation changes nothing. Refusals raise :class:`RegistryError` with a
one-line reason.

Rights only ever shrink safely: whenever an operation takes rights away from a
manager (revoke a grant, disable it, change its certificate, remove it, an import
that does any of these), every token issued to it that has not expired yet is
revoked too, so the revocation feed cuts it off within one poll instead of at token
expiry.

Every change (a manager added, enabled, disabled, removed or given a new certificate,
a grant added or removed, a policy import, a signing key rotation, a token revoked)
writes one ``registry_change`` row in its own transaction: who (OS user, host,
command; :class:`~authz_server.changes.ChangeSource`) changed what (before and after,
as JSON). A refused change writes none, and a call that changes nothing writes none.
The rows are hash-chained; appends are serialized (``BEGIN IMMEDIATE`` on SQLite, a
transaction-scoped advisory lock on PostgreSQL) so concurrent writers cannot fork the
chain, and :meth:`Registry.verify_changes` walks it.
"""

from __future__ import annotations

import json
import re
import secrets
import sys
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import Engine, and_, delete, func, insert, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, selectinload

from authz_server import changes
from authz_server import keys as keymod
from authz_server.changes import ChangeSource
from authz_server.db import session_factory
from authz_server.models import (
    GRANT_TABLES,
    AuditLog,
    Manager,
    Observation,
    RegistryChange,
    RegistryState,
    RevokedToken,
    SigningKey,
)
from cryptoros.errors import ConfigError, CryptorosError, RegistryError
from cryptoros.names import PARAM_TYPE, validate_graph_name, validate_namespace, validate_node_name, validate_type

ACTIONS = ("publish", "subscribe", "serve", "call", "read_param", "write_param")
#: the longest learning window (seconds)
MAX_LEARNING_S = 24 * 3600
#: a learned request reported this long after its window ended is still taken (seconds)
LEARNING_REPORT_SLACK = 60
#: observations kept per manager
MAX_OBSERVATIONS = 20_000
PARAM_ACTIONS = ("read_param", "write_param")


def grant_key(action: str) -> str:
    """The YAML key naming what a grant of ``action`` is on."""
    if action in PARAM_ACTIONS:
        return "namespace"
    return "topic" if action in ("publish", "subscribe") else "service"
_MANAGER_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,127}$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
POLICY_VERSION = 1
REVOCATION_SERIAL = "revocation_serial"
#: bumped by every change to a manager, its certificate or its grants: a replica keeps a
#: manager's grants cached for as long as this has not moved (the feed watcher reads it)
REGISTRY_VERSION = "registry_version"
#: longest a renewed certificate's predecessor may stay accepted (``set-cert --overlap``)
MAX_CERT_OVERLAP_S = 86400
#: the ``seq`` of the last registry_change row (a row cut from the chain's end shows)
CHANGE_CHAIN = "change_chain"
#: the highest CRL number any replica applied: a server started on an older copy of the
#: CRL would un-revoke the certificates revoked after it
CRL_NUMBER = "crl_number"
#: PostgreSQL advisory lock key serializing the change chain's appends (per database)
_CHAIN_LOCK_KEY = 0x63727970746F7273  # "cryptors"


def _now() -> datetime:
    return datetime.now(UTC)


def validate_manager_name(name: str) -> str:
    if not isinstance(name, str) or not _MANAGER_NAME.match(name):
        raise RegistryError(
            f"invalid manager name {name!r}: letters, digits, '_', '.', '-', starting with a letter"
        )
    return name


def normalize_fingerprint(fp: str) -> str:
    """Lowercase hex SHA-256; ``AA:BB:...`` (openssl's form) is accepted too."""
    norm = fp.strip().replace(":", "").lower() if isinstance(fp, str) else ""
    if not _HEX64.match(norm):
        raise RegistryError(f"invalid certificate fingerprint {fp!r}: expected 64 hex digits (SHA-256)")
    return norm


def validate_action(action: str) -> str:
    if action not in ACTIONS:
        raise RegistryError(f"invalid action {action!r}: expected one of {', '.join(ACTIONS)}")
    return action


@dataclass(frozen=True, order=True)
class GrantRow:
    """One validated grant: ``node`` may ``action`` on ``name`` with data type ``type``."""

    action: str
    node: str
    name: str
    type: str

    @classmethod
    def checked(cls, action: str, node: str, name: str, type_: str | None) -> GrantRow:
        validate_action(action)
        if action in PARAM_ACTIONS:  # a namespace; parameters carry no type
            if type_ not in (None, PARAM_TYPE):
                raise RegistryError(f"a {action} grant takes no type (got {type_!r})")
            return cls(action, validate_node_name(node), validate_namespace(name), PARAM_TYPE)
        if type_ is None:
            raise RegistryError(f"a {action} grant needs a data type")
        what = "topic" if action in ("publish", "subscribe") else "service name"
        return cls(action, validate_node_name(node), validate_graph_name(name, what), validate_type(type_))


@dataclass(frozen=True)
class ManagerInfo:
    name: str
    fingerprint: str | None
    enabled: bool
    created_at: datetime
    grants: tuple[GrantRow, ...] = field(default=())
    #: a renewed certificate's predecessor, accepted until ``previous_until`` (Unix seconds)
    previous_fingerprint: str | None = None
    previous_until: int | None = None
    #: the registry's version read just before this (:meth:`Registry.lookup_fingerprint`):
    #: what a token built from it is checked against when its row is stored
    version: int | None = None


@dataclass(frozen=True)
class ObservationRow:
    """One observation (:class:`~authz_server.models.Observation`) as read."""

    manager: str
    allowed: bool
    action: str
    node: str
    name: str
    type: str | None
    count: int
    first_seen: int
    last_seen: int


@dataclass(frozen=True)
class ActiveKey:
    kid: str
    private_pem: bytes
    encrypted: bool


@dataclass(frozen=True)
class PublicKeyRow:
    kid: str
    public_pem: str
    active: bool
    created_at: datetime
    retired_at: datetime | None


@dataclass(frozen=True)
class RevocationFeed:
    serial: int
    revoked_jtis: tuple[str, ...]
    disabled_managers: tuple[str, ...]
    #: the registry's REGISTRY_VERSION when this was read (not served: the replicas' own)
    registry_version: int = 0
    #: (manager, until) of every learning window not ended yet
    learning: tuple[tuple[str, int], ...] = ()


@dataclass(frozen=True)
class AuditEntry:
    """An audit row to write: a token issued, or a request refused with a reason."""

    event: str  # "issued" | "denied"
    manager: str | None
    cert_fingerprint: str | None
    remote: str | None
    reason: str = ""
    jti: str | None = None
    kid: str | None = None
    expires_at: int | None = None
    at: datetime = field(default_factory=_now)
    #: an issued token: the registry version its grants were read at; :meth:`Registry.record`
    #: stores the row only if no change committed since (else the token must not be handed out)
    version: int | None = None


@dataclass(frozen=True)
class ChangeEntry:
    """One registry change as recorded: ``before`` and ``after`` are decoded JSON."""

    seq: int
    at: datetime
    os_user: str
    host: str
    command: str
    target: str
    before: object
    after: object
    hash: str


@dataclass(frozen=True)
class ChainReport:
    """What :meth:`Registry.verify_changes` found: ``problem`` is None when intact."""

    rows: int
    head: str
    problem: str | None = None


def _default_source() -> ChangeSource:
    return ChangeSource.here(Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python")


def _grant_text(g: GrantRow) -> str:
    """A grant in a change record: ``publish /talker /chatter std_msgs/String``."""
    return f"{g.action} {g.node} {g.name} {g.type}"


def _grants_of(m: Manager) -> tuple[GrantRow, ...]:
    rows = []
    for action, (_cls, column, rel) in GRANT_TABLES.items():
        for g in getattr(m, rel):
            rows.append(GrantRow(action, g.name, getattr(g, column), g.data_type))
    return tuple(sorted(rows))


def _bound_to(fp: str, now: float):
    """The managers a certificate fingerprint is bound to at ``now``: as its certificate,
    or as the previous one a renewal's overlap still accepts."""
    return or_(Manager.cert_fingerprint == fp,
               and_(Manager.previous_fingerprint == fp, Manager.previous_until > int(now)))


def _info(m: Manager, with_grants: bool = True) -> ManagerInfo:
    previous = m.previous_fingerprint if m.previous_until is not None and m.previous_until > time.time() else None
    return ManagerInfo(m.name, m.cert_fingerprint, m.enabled, m.created_at, _grants_of(m) if with_grants else (),
                       previous, m.previous_until if previous else None)


class _DryRun(CryptorosError):
    """Rolls an import's transaction back once its counts are known (never leaves
    :meth:`Registry.import_policy`)."""


class Registry:
    """The registry on one database engine."""

    def __init__(self, engine: Engine, *, source: ChangeSource | None = None) -> None:
        self.engine = engine
        self._session = session_factory(engine)
        #: who the changes made through this handle are recorded as made by
        self.source = source or _default_source()

    # ------------------------------------------------------------------ the change record
    @contextmanager
    def _changing(self) -> Iterator[Session]:
        """A transaction that may change the registry: it holds the change chain's lock
        from its start, so its reads of the state before are not stale and its change
        row follows the last one committed."""
        with self._locked(shared=False) as s:
            yield s

    @contextmanager
    def _issuing(self) -> Iterator[Session]:
        """A transaction that stores issued tokens: it holds the change lock shared (many
        at once, never during a change), so the registry's version it reads stays the
        version until it commits (:meth:`record`)."""
        with self._locked(shared=True) as s:
            yield s

    @contextmanager
    def _locked(self, *, shared: bool) -> Iterator[Session]:
        """A transaction holding the change lock from its start: alone, or ``shared`` with
        other shared holders (SQLite has one writer at a time either way: the write lock
        now, not at the first write)."""
        with self._session.begin() as s:
            backend = self.engine.dialect.name
            if backend == "sqlite":
                s.connection().exec_driver_sql("BEGIN IMMEDIATE")
            elif backend == "postgresql":
                lock = func.pg_advisory_xact_lock_shared if shared else func.pg_advisory_xact_lock
                s.execute(select(lock(_CHAIN_LOCK_KEY)))
            else:  # pragma: no cover - the registry runs on SQLite or PostgreSQL
                s.get(RegistryState, CHANGE_CHAIN, with_for_update={"read": True} if shared else True)
            yield s

    @staticmethod
    def _version(s: Session) -> int:
        row = s.get(RegistryState, REGISTRY_VERSION)
        return row.value if row is not None else 0

    def _log_change(self, s: Session, target: str, before: object, after: object) -> None:
        """Append one change row (in ``s``, inside :meth:`_changing`)."""
        last = s.execute(select(RegistryChange.seq, RegistryChange.hash)
                         .order_by(RegistryChange.seq.desc()).limit(1)).first()
        head = s.get(RegistryState, CHANGE_CHAIN)
        # numbered after the head counter: rows cut from the end stay a gap the next row shows
        seq = max(head.value if head is not None else 0, last.seq if last else 0) + 1
        prev = last.hash if last else changes.GENESIS
        src = self.source
        row = {"seq": seq, "at": _now(), "os_user": src.os_user, "host": src.host, "command": src.command,
               "target": target[:256], "before": changes.to_json(before), "after": changes.to_json(after),
               "prev_hash": prev}
        s.execute(insert(RegistryChange), [{**row, "hash": changes.row_hash(**row)}])
        if head is None:
            s.add(RegistryState(key=CHANGE_CHAIN, value=seq))
        else:
            head.value = seq

    def _states(self, s: Session, names: Iterable[str] | None = None) -> dict[str, dict]:
        """The managers' states as a change records them, read from the database (after
        a flush: what this transaction wrote is included)."""
        q = select(Manager)
        if names is not None:
            q = q.where(Manager.name.in_(list(names)))
        s.flush()
        ms = list(s.scalars(q))
        grants: dict[int, list[str]] = {m.id: [] for m in ms}
        for action, (cls, column, _rel) in GRANT_TABLES.items():
            for mid, node, name, type_ in s.execute(select(cls.manager_id, cls.name, getattr(cls, column),
                                                           cls.data_type).where(cls.manager_id.in_(list(grants)))):
                grants[mid].append(_grant_text(GrantRow(action, node, name, type_)))
        return {m.name: {"fingerprint": m.cert_fingerprint, "enabled": m.enabled,
                         "previous_fingerprint": m.previous_fingerprint, "previous_until": m.previous_until,
                         "grants": sorted(grants[m.id])} for m in ms}

    def _state(self, s: Session, name: str) -> dict | None:
        return self._states(s, [name]).get(name)

    def changes(self, *, since: datetime | None = None, limit: int | None = None) -> list[ChangeEntry]:
        """Recorded changes, oldest first (the last ``limit`` of them)."""
        with self._session() as s:
            q = select(RegistryChange).order_by(RegistryChange.seq.desc())
            if since is not None:
                q = q.where(RegistryChange.at >= since)
            if limit is not None:
                q = q.limit(limit)
            rows = list(s.scalars(q))
        rows.reverse()
        return [ChangeEntry(r.seq, r.at if r.at.tzinfo else r.at.replace(tzinfo=UTC), r.os_user, r.host, r.command,
                            r.target, _loads(r.before), _loads(r.after), r.hash) for r in rows]

    def verify_changes(self) -> ChainReport:
        """Walk the change chain from its first row: every row's hash must match its
        content, its ``prev_hash`` the row before it, its ``seq`` the next number, and
        the last row the chain head counter. One consistent snapshot of the table."""
        with self._session() as s:
            if self.engine.dialect.name == "sqlite":
                s.connection().exec_driver_sql("BEGIN")  # one read snapshot for the walk
            else:
                s.connection(execution_options={"isolation_level": "REPEATABLE READ"})
            head_row = s.get(RegistryState, CHANGE_CHAIN)
            head_seq = head_row.value if head_row is not None else 0
            prev, n = changes.GENESIS, 0
            for r in s.execute(select(RegistryChange).order_by(RegistryChange.seq)
                               .execution_options(yield_per=1000)).scalars():
                n += 1
                expect = changes.row_hash(seq=r.seq, at=r.at, os_user=r.os_user, host=r.host, command=r.command,
                                          target=r.target, before=r.before, after=r.after, prev_hash=r.prev_hash)
                if expect != r.hash:
                    return ChainReport(n - 1, prev, f"row {r.seq}: its content does not match its hash "
                                                    "(the row was edited)")
                if r.seq != n:
                    return ChainReport(n - 1, prev, f"row {r.seq}: expected row {n} here "
                                                    "(a row is missing before it)")
                if r.prev_hash != prev:
                    return ChainReport(n - 1, prev, f"row {r.seq}: does not follow the row before it "
                                                    "(a row before it was deleted, inserted or rewritten)")
                prev = r.hash
            if head_seq != n:
                return ChainReport(n, prev, f"the chain head records {head_seq} row(s) but {n} are there "
                                            "(rows cut from its end, or the head edited)")
            return ChainReport(n, prev)

    # ------------------------------------------------------------------ helpers
    def _manager(self, s: Session, name: str, *, load_grants: bool = False) -> Manager:
        validate_manager_name(name)
        q = select(Manager).where(Manager.name == name)
        if load_grants:
            q = q.options(*(selectinload(getattr(Manager, rel)) for _c, _col, rel in GRANT_TABLES.values()))
        m = s.scalars(q).one_or_none()
        if m is None:
            raise RegistryError(f"unknown manager {name!r}")
        return m

    def crl_number(self, ca: str) -> int:
        """The highest number of CA ``ca``'s CRLs (its certificate's SHA-256) a server of
        this registry applied (0: none yet)."""
        with self._session() as s:
            row = s.get(RegistryState, f"{CRL_NUMBER}:{ca[:32]}")
            return row.value if row is not None else 0

    def note_crl_number(self, ca: str, number: int) -> None:
        """Remember ``number`` for CA ``ca`` if it is higher than any applied before."""
        key = f"{CRL_NUMBER}:{ca[:32]}"
        with self._session.begin() as s:
            row = s.get(RegistryState, key, with_for_update=True)
            if row is None:
                s.add(RegistryState(key=key, value=number))
            elif number > row.value:
                row.value = number

    def _bump_serial(self, s: Session, key: str = REVOCATION_SERIAL) -> None:
        row = s.get(RegistryState, key, with_for_update=True)
        if row is None:
            s.add(RegistryState(key=key, value=1))
        else:
            row.value = row.value + 1

    def _managers_changed(self, s: Session) -> None:
        """A manager, its certificate or its grants changed in this transaction: every
        replica's cached lookups are dropped once its feed watcher reads the new version."""
        self._bump_serial(s, REGISTRY_VERSION)

    def _revoke_outstanding(self, s: Session, manager: str, reason: str) -> int:
        """Revoke every unexpired token issued to ``manager``; return how many."""
        now = int(time.time())
        rows = s.execute(
            select(AuditLog.jti, AuditLog.expires_at).where(
                AuditLog.event == "issued", AuditLog.manager == manager, AuditLog.expires_at > now
            )
        ).all()
        if not rows:
            return 0
        have = set(s.scalars(select(RevokedToken.jti).where(RevokedToken.jti.in_([r.jti for r in rows]))))
        added = 0
        for jti, exp in rows:
            if jti and jti not in have:
                s.add(RevokedToken(jti=jti, expires_at=exp, revoked_at=_now(), reason=reason))
                have.add(jti)
                added += 1
        if added:
            self._bump_serial(s)
        return added

    # ------------------------------------------------------------------ managers
    def add_manager(self, name: str, fingerprint: str | None, *, enabled: bool = True) -> ManagerInfo:
        validate_manager_name(name)
        fp = normalize_fingerprint(fingerprint) if fingerprint is not None else None
        with self._changing() as s:
            if s.scalars(select(Manager.id).where(Manager.name == name)).first() is not None:
                raise RegistryError(f"manager {name!r} already exists")
            if fp is not None:
                self._check_fp_free(s, fp, name)
            m = Manager(name=name, cert_fingerprint=fp, enabled=enabled, created_at=_now())
            s.add(m)
            self._managers_changed(s)  # a replica may have cached its certificate as unknown
            if not enabled:
                self._bump_serial(s)
            self._log_change(s, f"manager {name}", None, self._state(s, name))
            return _info(m, with_grants=False)

    def _check_fp_free(self, s: Session, fp: str, name: str) -> None:
        """A certificate is bound to one manager at most: as its certificate, or as the
        previous one it still accepts (``set-cert --overlap``)."""
        owner = s.scalars(select(Manager.name).where(_bound_to(fp, time.time()))).first()
        if owner is not None and owner != name:
            raise RegistryError(f"certificate {fp[:16]}... is already bound to manager {owner!r}")

    def set_cert(self, name: str, fingerprint: str, *, overlap: float = 0.0) -> int:
        """Bind ``name`` to a new certificate. With no ``overlap``, the old one is refused
        at once and every outstanding token of the manager revoked (a key that may be
        compromised). With ``overlap`` seconds, a planned renewal: the old certificate is
        still accepted that long and no token is revoked, so the robot's interceptor
        keeps its streams and tokens until it reloads with the new one (its old
        certificate's tokens expire on their own; revoke its serial at the CA to end it
        early everywhere). Returns the tokens revoked."""
        fp = normalize_fingerprint(fingerprint)
        if not 0 <= overlap <= MAX_CERT_OVERLAP_S:
            raise RegistryError(f"overlap must be 0 to {MAX_CERT_OVERLAP_S} seconds, got {overlap!r}")
        with self._changing() as s:
            m = self._manager(s, name)
            self._check_fp_free(s, fp, name)
            if m.cert_fingerprint == fp and not (overlap == 0 and m.previous_fingerprint):
                return 0
            before = self._state(s, name)
            revoked = 0
            if overlap > 0:
                if m.cert_fingerprint != fp:
                    m.previous_fingerprint, m.previous_until = m.cert_fingerprint, int(time.time() + overlap)
                m.cert_fingerprint = fp
            else:
                m.cert_fingerprint, m.previous_fingerprint, m.previous_until = fp, None, None
                revoked = self._revoke_outstanding(s, name, "certificate replaced")
            self._managers_changed(s)
            self._log_manager_change(s, name, before, revoked)
            return revoked

    def set_enabled(self, name: str, enabled: bool) -> bool:
        """Enable or disable; return whether anything changed."""
        with self._changing() as s:
            m = self._manager(s, name)
            if m.enabled == enabled:
                return False
            before = self._state(s, name)
            m.enabled = enabled
            self._bump_serial(s)
            self._managers_changed(s)
            revoked = 0 if enabled else self._revoke_outstanding(s, name, "manager disabled")
            self._log_manager_change(s, name, before, revoked)
            return True

    def remove_manager(self, name: str) -> None:
        with self._changing() as s:
            m = self._manager(s, name)
            before = self._state(s, name)
            revoked = self._revoke_outstanding(s, name, "manager removed")
            s.delete(m)
            self._managers_changed(s)
            self._log_change(s, f"manager {name}", before, {"tokens_revoked": revoked} if revoked else None)

    def list_managers(self) -> list[ManagerInfo]:
        with self._session() as s:
            ms = s.scalars(
                select(Manager)
                .options(*(selectinload(getattr(Manager, rel)) for _c, _col, rel in GRANT_TABLES.values()))
                .order_by(Manager.name)
            ).all()
            return [_info(m) for m in ms]

    def get_manager(self, name: str) -> ManagerInfo:
        with self._session() as s:
            return _info(self._manager(s, name, load_grants=True))

    def lookup_fingerprint(self, fingerprint: str, *, now: float | None = None) -> ManagerInfo | None:
        """The manager bound to a certificate fingerprint, with its grants (daemon path):
        its certificate, or the one it renewed while the overlap lasts."""
        now = time.time() if now is None else now
        with self._session() as s:
            version = self._version(s)  # read first: the grants below are at least this recent
            m = s.scalars(
                select(Manager)
                .where(_bound_to(fingerprint, now))
                .options(*(selectinload(getattr(Manager, rel)) for _c, _col, rel in GRANT_TABLES.values()))
            ).one_or_none()
            return None if m is None else replace(_info(m), version=version)

    # ------------------------------------------------------------------ grants
    def grant(self, manager: str, action: str, node: str, name: str, type_: str | None) -> bool:
        """Add a grant; return False if it was already there."""
        return self.grant_many(manager, [GrantRow.checked(action, node, name, type_)])[0]

    def grant_many(self, manager: str, rows: Iterable[GrantRow], *, remove: bool = False) -> list[bool]:
        """Add (or with ``remove`` take away) several grants of one manager in one
        transaction, one change row; return, for each, whether it changed anything (a
        grant already there, or absent for ``remove``, is left as it is). Taking one away
        revokes the manager's live tokens."""
        rows = list(rows)
        with self._changing() as s:
            m = self._manager(s, manager)
            before = self._state(s, manager)
            done = [self._remove_grant(s, m, g) if remove else self._add_grant(s, m, g) for g in rows]
            if not any(done):
                return done
            revoked = 0
            if remove:
                revoked = self._revoke_outstanding(s, manager, "grant revoked")
            else:
                self._bump_serial(s)  # the feed changes: interceptors fetch tokens with the new grant
            self._managers_changed(s)
            self._log_manager_change(s, manager, before, revoked)
            return done

    def _remove_grant(self, s: Session, m: Manager, g: GrantRow) -> bool:
        cls, column, _rel = GRANT_TABLES[g.action]
        return bool(s.execute(delete(cls).where(cls.manager_id == m.id, cls.name == g.node,
                                                getattr(cls, column) == g.name, cls.data_type == g.type)).rowcount)

    def _log_manager_change(self, s: Session, name: str, before: dict, tokens_revoked: int = 0) -> None:
        """Record what changed in manager ``name`` (still there) since ``before``."""
        b, a = changes.diff(before, self._state(s, name))
        assert b is not None and a is not None
        if b == a == {} and not tokens_revoked:
            return
        if tokens_revoked:
            a["tokens_revoked"] = tokens_revoked
        self._log_change(s, f"manager {name}", b, a)

    def _add_grant(self, s: Session, m: Manager, g: GrantRow) -> bool:
        cls, column, _rel = GRANT_TABLES[g.action]
        exists = s.scalars(
            select(cls.id).where(
                cls.manager_id == m.id, cls.name == g.node, getattr(cls, column) == g.name, cls.data_type == g.type
            )
        ).first()
        if exists is not None:
            return False
        s.add(cls(manager_id=m.id, name=g.node, data_type=g.type, **{column: g.name}))
        return True

    def revoke(self, manager: str, action: str, node: str, name: str, type_: str | None = None) -> int:
        """Remove matching grants (any type when ``type_`` is None); revoke live tokens.

        Removing nothing is an error: the operator named a grant that does not exist.
        """
        validate_action(action)
        validate_node_name(node)
        if action in PARAM_ACTIONS:
            validate_namespace(name)
            type_ = None
        else:
            validate_graph_name(name, "topic" if action in ("publish", "subscribe") else "service name")
        if type_ is not None:
            validate_type(type_)
        cls, column, _rel = GRANT_TABLES[action]
        with self._changing() as s:
            m = self._manager(s, manager)
            before = self._state(s, manager)
            q = delete(cls).where(cls.manager_id == m.id, cls.name == node, getattr(cls, column) == name)
            if type_ is not None:
                q = q.where(cls.data_type == type_)
            removed = s.execute(q).rowcount
            if not removed:
                raise RegistryError(f"manager {manager!r} has no {action} grant for {node} on {name}"
                                    + (f" with type {type_}" if type_ else ""))
            self._managers_changed(s)
            revoked = self._revoke_outstanding(s, manager, f"{action} grant revoked")
            self._log_manager_change(s, manager, before, revoked)
            return removed

    # ------------------------------------------------------------------ policy as YAML
    def export_policy(self) -> dict:
        managers = []
        for m in self.list_managers():
            grants: dict[str, list[dict]] = {a: [] for a in ACTIONS}
            for g in m.grants:
                row = {"node": g.node, grant_key(g.action): g.name}
                if g.action not in PARAM_ACTIONS:
                    row["type"] = g.type
                grants[g.action].append(row)
            managers.append(
                {
                    "name": m.name,
                    "fingerprint_sha256": m.fingerprint,
                    "enabled": m.enabled,
                    "grants": {a: v for a, v in grants.items() if v},
                }
            )
        return {"version": POLICY_VERSION, "managers": managers}

    def import_policy(self, policy: object, *, merge: bool = False, dry_run: bool = False) -> dict[str, int]:
        """Counts of what :meth:`import_policy_report` changed."""
        return self.import_policy_report(policy, merge=merge, dry_run=dry_run).stats

    def import_policy_report(self, policy: object, *, merge: bool = False, dry_run: bool = False) -> PolicyImport:
        """Make the registry's policy equal to ``policy`` (or only add, with ``merge``).

        A manager the policy names without a ``fingerprint_sha256`` key keeps its
        certificate; an explicit null unbinds it (not on a merge). The whole document is
        validated before anything is written; the change is one transaction. Returns
        what changed (``dry_run``: would change; the transaction is rolled back).
        """
        wanted = parse_policy(policy)
        report = PolicyImport()
        stats = report.stats
        fps = [w.fingerprint for w in wanted.values() if w.fingerprint]
        if len(fps) != len(set(fps)):
            raise RegistryError("policy binds one certificate fingerprint to two managers")
        try:
            with self._changing() as s:
                existing = {
                    m.name: m
                    for m in s.scalars(
                        select(Manager).options(
                            *(selectinload(getattr(Manager, rel)) for _c, _col, rel in GRANT_TABLES.values())
                        )
                    )
                }
                before = self._states(s)
                orig_fp = {name: m.cert_fingerprint for name, m in existing.items()}
                target_fp = {name: _target_fingerprint(w, orig_fp.get(name), merge=merge, known=name in existing)
                              for name, w in wanted.items()}
                _check_one_manager_per_certificate(wanted, target_fp)
                if merge:
                    for name, fp in orig_fp.items():
                        if name not in wanted and fp is not None and fp in target_fp.values():
                            other = next(n for n, t in target_fp.items() if t == fp)
                            raise RegistryError(f"policy binds the certificate of manager {name!r} to manager "
                                                f"{other!r} too: one certificate, one manager")
                else:
                    for name, m in existing.items():
                        if name not in wanted:
                            stats["tokens_revoked"] += self._revoke_outstanding(s, name, "manager removed by import")
                            s.delete(m)
                            stats["managers_removed"] += 1
                            report.managers_removed.append(name)
                # Free changing fingerprints first so swapping certificates between managers works.
                # A policy names one certificate per manager: a renewal's overlap ends with it.
                for name, m in existing.items():
                    if name in wanted and target_fp[name] != orig_fp[name]:
                        m.cert_fingerprint = m.previous_fingerprint = m.previous_until = None
                    elif m.previous_fingerprint is not None and m.previous_fingerprint in target_fp.values():
                        m.previous_fingerprint = m.previous_until = None
                s.flush()
                for name, w in wanted.items():
                    m = existing.get(name)
                    have: set[GrantRow] = set()
                    if m is None:
                        enabled = w.enabled is not False
                        m = Manager(name=name, cert_fingerprint=w.fingerprint, enabled=enabled, created_at=_now())
                        s.add(m)
                        s.flush()
                        stats["managers_added"] += 1
                        report.managers_added.append((name, w.fingerprint))
                        if not enabled:
                            self._bump_serial(s)
                    else:
                        have = set(_grants_of(m))
                        changed = shrink = False
                        m.cert_fingerprint = target_fp[name]
                        if target_fp[name] != orig_fp[name]:
                            changed = shrink = True
                            report.certificates.append((name, orig_fp[name], target_fp[name]))
                        # a merge that does not say 'enabled' leaves it: an import never
                        # re-enables a manager an operator disabled meanwhile
                        enabled = m.enabled if (w.enabled is None and merge) else w.enabled is not False
                        if m.enabled != enabled:
                            report.enabled.append((name, enabled))
                            m.enabled = enabled
                            self._bump_serial(s)
                            changed = True
                            shrink = shrink or not enabled
                        if not merge:
                            for g in sorted(have - w.grants):
                                cls, column, _rel = GRANT_TABLES[g.action]
                                s.execute(delete(cls).where(
                                    cls.manager_id == m.id, cls.name == g.node,
                                    getattr(cls, column) == g.name, cls.data_type == g.type))
                                stats["grants_removed"] += 1
                                report.grants_removed.append((name, g))
                                shrink = True
                        if shrink:
                            stats["tokens_revoked"] += self._revoke_outstanding(s, name, "policy import")
                        if changed:
                            stats["managers_changed"] += 1
                    for g in sorted(w.grants - have):
                        self._add_grant(s, m, g)
                        stats["grants_added"] += 1
                        report.grants_added.append((name, g))
                if any(stats.values()):
                    self._managers_changed(s)
                    self._log_policy_change(s, before, stats["tokens_revoked"])
                if dry_run:
                    raise _DryRun
        except _DryRun:
            pass
        except IntegrityError as exc:  # pragma: no cover - guarded by the checks above
            raise RegistryError(f"policy conflicts with the registry: {exc.orig}") from exc
        return report

    def _log_policy_change(self, s: Session, before: dict[str, dict], tokens_revoked: int) -> None:
        """One change row for an import: per manager that changed, what changed."""
        after = self._states(s)
        b_all: dict[str, object] = {}
        a_all: dict[str, object] = {}
        for name in sorted(before.keys() | after.keys()):
            b, a = changes.diff(before.get(name), after.get(name))
            if not b == a == {}:
                b_all[name], a_all[name] = b, a
        extra = {"tokens_revoked": tokens_revoked} if tokens_revoked else {}
        self._log_change(s, "policy", {"managers": b_all}, {"managers": a_all, **extra})

    # ------------------------------------------------------------------ signing keys
    def rotate_key(self, prot: keymod.KeyProtection, bits: int = keymod.RSA_BITS, *,
                   change_passphrase: bool = False) -> str:
        """Create a new active signing key; the previous one is retired (still published).

        The passphrase must open the current active key (the one ``serve`` was given):
        a new key under another passphrase would stop the next ``serve`` from starting.
        ``change_passphrase`` says the operator means to restart ``serve`` with the new one."""
        current = self.active_key()
        if current is not None and not change_passphrase:
            try:
                keymod.load_private(current.private_pem, current.encrypted, prot, current.kid)
            except ConfigError:
                raise RegistryError(f"the passphrase given does not open the current signing key {current.kid}: "
                                    "give the one serve uses (or --change-passphrase, then restart serve "
                                    "with the new one)") from None
        new = keymod.generate(prot, bits)
        with self._changing() as s:
            old = list(s.scalars(select(SigningKey.kid).where(SigningKey.active.is_(True)).order_by(SigningKey.kid)))
            s.execute(update(SigningKey).where(SigningKey.active.is_(True)).values(active=False, retired_at=_now()))
            s.add(SigningKey(kid=new.kid, algorithm="RS256", private_pem=new.private_pem,
                             public_pem=new.public_pem, encrypted=new.encrypted, active=True,
                             created_at=_now()))
            self._log_change(s, "signing key", {"active": old[0] if len(old) == 1 else old or None},
                             {"active": new.kid, "encrypted": new.encrypted, "bits": bits})
        return new.kid

    def active_key(self) -> ActiveKey | None:
        with self._session() as s:
            k = s.scalars(select(SigningKey).where(SigningKey.active.is_(True))
                          .order_by(SigningKey.created_at.desc())).first()
            return None if k is None else ActiveKey(k.kid, k.private_pem, k.encrypted)

    def list_keys(self) -> list[PublicKeyRow]:
        with self._session() as s:
            return [PublicKeyRow(k.kid, k.public_pem, k.active, k.created_at, k.retired_at)
                    for k in s.scalars(select(SigningKey).order_by(SigningKey.created_at))]

    def published_keys(self, *, now: float, max_lifetime: int) -> list[PublicKeyRow]:
        """Keys the JWKS must list: the active one, and every retired key that signed a
        token still unexpired (per the audit log) or was retired less than
        ``max_lifetime`` seconds ago (covers a token signed just before the rotation)."""
        now_i = int(now)
        with self._session() as s:
            out = []
            for k in s.scalars(select(SigningKey).order_by(SigningKey.created_at.desc())):
                retired = k.retired_at
                if retired is not None and retired.tzinfo is None:
                    retired = retired.replace(tzinfo=UTC)
                keep = k.active or (retired is not None and retired.timestamp() > now - max_lifetime)
                if not keep:
                    # uses the (kid, expires_at) index: cheap however long the audit log grows
                    keep = s.scalar(select(AuditLog.id).where(
                        AuditLog.kid == k.kid, AuditLog.expires_at > now_i).limit(1)) is not None
                if keep:
                    out.append(PublicKeyRow(k.kid, k.public_pem, k.active, k.created_at, k.retired_at))
            return out

    # ------------------------------------------------------------------ revocation
    def revoke_token(self, jti: str, *, reason: str = "revoked by operator", expires_at: int | None = None) -> bool:
        """Revoke a token id. Its expiry comes from the audit log (or ``expires_at``)."""
        if not isinstance(jti, str) or not re.match(r"^[A-Za-z0-9_-]{8,64}$", jti):
            raise RegistryError(f"invalid token id {jti!r}")
        with self._changing() as s:
            exp = s.scalars(select(AuditLog.expires_at).where(AuditLog.jti == jti, AuditLog.event == "issued")).first()
            if exp is None:
                if expires_at is None:
                    raise RegistryError(f"unknown token id {jti!r} (not in the audit log; give --expires-at to revoke it anyway)")
                exp = expires_at
            if s.get(RevokedToken, jti) is not None:
                return False
            s.add(RevokedToken(jti=jti, expires_at=exp, revoked_at=_now(), reason=reason[:256]))
            self._bump_serial(s)
            self._log_change(s, f"token {jti}", None, {"revoked": True, "expires_at": exp, "reason": reason[:256]})
            return True

    def revocation_feed(self, *, now: float) -> RevocationFeed:
        with self._session() as s:
            counters = {key: value for key, value in s.execute(
                select(RegistryState.key, RegistryState.value)
                .where(RegistryState.key.in_((REVOCATION_SERIAL, REGISTRY_VERSION))))}
            serial = counters.get(REVOCATION_SERIAL) or 0
            jtis = tuple(s.scalars(select(RevokedToken.jti).where(RevokedToken.expires_at > int(now))
                                   .order_by(RevokedToken.jti)))
            disabled = tuple(s.scalars(select(Manager.name).where(Manager.enabled.is_(False)).order_by(Manager.name)))
            learning = tuple((name, until) for name, until in s.execute(
                select(Manager.name, Manager.learning_until)
                .where(Manager.learning_until > int(now)).order_by(Manager.name)))
            return RevocationFeed(serial, jtis, disabled, counters.get(REGISTRY_VERSION) or 0, learning)

    # ------------------------------------------------------------------ learning mode
    def set_learning(self, name: str, seconds: float | None, *, now: float | None = None) -> tuple[int, int] | None:
        """Put ``name`` in learning mode for ``seconds`` (at most :data:`MAX_LEARNING_S`),
        or end it (None). The feed carries the window to every interceptor. Returns the
        window (since, until), or None when it ended one (or there was none)."""
        now = int(time.time() if now is None else now)
        if seconds is not None and not 0 < seconds <= MAX_LEARNING_S:
            raise RegistryError(f"a learning window lasts 1 s to {MAX_LEARNING_S // 3600} h, not {seconds!r} s")
        with self._changing() as s:
            m = self._manager(s, name)
            active = m.learning_until is not None and m.learning_until > now
            if seconds is None and not active:
                return None
            before = {"learning_since": m.learning_since, "learning_until": m.learning_until}
            if seconds is None:
                m.learning_until = now
            else:
                m.learning_since = m.learning_since if active else now
                m.learning_until = now + int(seconds)
            self._bump_serial(s)
            self._log_change(s, f"manager {name} learning", before,
                             {"learning_since": m.learning_since, "learning_until": m.learning_until})
            return None if seconds is None else (m.learning_since, m.learning_until)

    def learning_window(self, name: str) -> tuple[int | None, int | None]:
        """``name``'s last learning window (since, until), ended or not."""
        with self._session() as s:
            m = self._manager(s, name)
            return m.learning_since, m.learning_until

    def record_observations(self, name: str, rows: Iterable[Mapping], *, now: float | None = None) -> tuple[int, int]:
        """Add what ``name``'s interceptor reports (rows validated by the caller:
        :func:`authz_server.learning.checked_observation`). A learned request is taken
        only while the manager learns (a report sent just after the end included:
        :data:`LEARNING_REPORT_SLACK`); a manager keeps at most :data:`MAX_OBSERVATIONS`
        rows. Returns (accepted, refused)."""
        now = int(time.time() if now is None else now)
        accepted = refused = 0
        with self._session.begin() as s:
            m = self._manager(s, name)
            learning = m.learning_until is not None and m.learning_until + LEARNING_REPORT_SLACK > now
            held = s.scalar(select(func.count(Observation.id)).where(Observation.manager_id == m.id)) or 0
            for r in rows:
                if not r["allowed"] and not learning:
                    refused += 1
                    continue
                key = (Observation.manager_id == m.id, Observation.allowed.is_(bool(r["allowed"])),
                       Observation.action == r["action"], Observation.node == r["node"],
                       Observation.name == r["name"], Observation.data_type == (r["type"] or ""))
                row = s.scalars(select(Observation).where(*key)).first()
                if row is None:
                    if held >= MAX_OBSERVATIONS:
                        refused += 1
                        continue
                    held += 1
                    s.add(Observation(manager_id=m.id, allowed=bool(r["allowed"]), action=r["action"], node=r["node"],
                                      name=r["name"], data_type=r["type"] or "", count=r["count"],
                                      first_seen=int(r["first"]), last_seen=int(r["last"])))
                else:
                    row.count = min(row.count + r["count"], 2**31 - 1)
                    row.first_seen, row.last_seen = min(row.first_seen, int(r["first"])), max(row.last_seen, int(r["last"]))
                accepted += 1
        return accepted, refused

    def observations(self, name: str | None = None, *, allowed: bool | None = None,
                     since: float | None = None) -> list[ObservationRow]:
        """Recorded observations (of one manager, of one kind, last seen at ``since`` or later)."""
        with self._session() as s:
            q = select(Manager.name, Observation).join(Manager, Manager.id == Observation.manager_id)
            if name is not None:
                q = q.where(Manager.name == validate_manager_name(name))
            if allowed is not None:
                q = q.where(Observation.allowed.is_(allowed))
            if since is not None:
                q = q.where(Observation.last_seen >= int(since))
            return [ObservationRow(mname, o.allowed, o.action, o.node, o.name, o.data_type or None, o.count,
                                   o.first_seen, o.last_seen)
                    for mname, o in s.execute(q.order_by(Manager.name, Observation.action, Observation.node,
                                                         Observation.name))]

    # ------------------------------------------------------------------ audit
    def record(self, entries: Iterable[AuditEntry]) -> list[bool]:
        """Store audit rows in one transaction (one INSERT of many rows: no ORM objects,
        this is the daemon's per-token write); for each entry, whether it was stored.

        An issued token's row (``version`` set) is stored only if the registry's version is
        still the one its grants were read at. The check and the insert hold the change
        lock shared (:meth:`_changing` holds it alone), so a change either committed
        before, and the row is refused (the caller must not hand the token out: it may
        carry a grant just taken away), or comes after, and revokes the stored token with
        the manager's others (:meth:`_revoke_outstanding` reads these rows). Without the
        check, a token built from a replica's kept grants in the moments after a revoke
        would carry the removed grant, unrevoked, for its whole lifetime."""
        entries = list(entries)
        if not entries:
            return []
        checked = any(e.version is not None for e in entries)
        with (self._issuing() if checked else self._session.begin()) as s:
            current = self._version(s) if checked else None
            stored = [e.version is None or e.version == current for e in entries]
            rows = [
                {"at": e.at, "event": e.event, "manager": e.manager, "cert_fingerprint": e.cert_fingerprint,
                 "remote": e.remote, "reason": e.reason[:256], "jti": e.jti, "kid": e.kid, "expires_at": e.expires_at}
                for e, ok in zip(entries, stored) if ok
            ]
            if rows:
                s.execute(insert(AuditLog), rows)
        return stored

    def prune_audit(self, *, keep_days: float, max_rows: int, now: float | None = None) -> int:
        """Bound the audit log: delete rows older than ``keep_days`` and, beyond
        ``max_rows``, the oldest ones; never a row of a token not yet expired (the JWKS
        keeps a retired key published while such a token lives). Revoked-token rows go
        a day after the token's expiry. Returns rows deleted."""
        now_i = int(time.time() if now is None else now)
        done = or_(AuditLog.expires_at.is_(None), AuditLog.expires_at < now_i)
        cutoff = datetime.fromtimestamp(now_i - keep_days * 86400, tz=UTC)
        with self._session.begin() as s:
            deleted = s.execute(delete(AuditLog).where(AuditLog.at < cutoff, done)).rowcount or 0
            threshold = s.scalar(select(AuditLog.id).order_by(AuditLog.id.desc()).offset(max_rows).limit(1))
            if threshold is not None:
                deleted += s.execute(delete(AuditLog).where(AuditLog.id <= threshold, done)).rowcount or 0
            # revoked tokens a day past their expiry: no verifier accepts them anyway
            deleted += s.execute(delete(RevokedToken).where(RevokedToken.expires_at < now_i - 86400)).rowcount or 0
        return deleted

    def audit(self, *, limit: int = 50, manager: str | None = None, event: str | None = None,
              since: datetime | None = None) -> list[AuditEntry]:
        with self._session() as s:
            q = select(AuditLog).order_by(AuditLog.id.desc()).limit(limit)
            if since is not None:
                q = q.where(AuditLog.at >= since)
            if manager is not None:
                q = q.where(AuditLog.manager == manager)
            if event is not None:
                q = q.where(AuditLog.event == event)
            rows = list(s.scalars(q))
        rows.reverse()
        return [AuditEntry(r.event, r.manager, r.cert_fingerprint, r.remote, r.reason, r.jti, r.kid, r.expires_at,
                           r.at if r.at.tzinfo else r.at.replace(tzinfo=UTC)) for r in rows]

    def ping(self) -> None:
        with self._session() as s:
            s.scalar(select(func.count()).select_from(RegistryState))


def _loads(text: str | None) -> object:
    return None if text is None else json.loads(text)


def new_jti() -> str:
    """128 random bits in hex: never starts with '-', so ``cryptoros-authz revoke-token JTI``
    cannot mistake a token id for an option (base64url ids did, one in 64)."""
    return secrets.token_hex(16)


# ---------------------------------------------------------------------- policy parsing
@dataclass(frozen=True)
class WantedManager:
    name: str
    fingerprint: str | None
    enabled: bool | None  # None: not said (true, or on a merge the manager's own state)
    grants: frozenset[GrantRow]
    # False: the file has no fingerprint_sha256 key, and a manager the registry holds
    # keeps its certificate (hand-written policies leave the key out)
    fingerprint_given: bool = True


@dataclass
class PolicyImport:
    """What an import changed (or, in a dry run, would change): the counts, and each
    manager and grant it touched, in the order it touched them."""

    stats: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ("managers_added", "managers_removed", "managers_changed", "grants_added", "grants_removed",
         "tokens_revoked"), 0))
    managers_added: list[tuple[str, str | None]] = field(default_factory=list)  # (name, fingerprint)
    managers_removed: list[str] = field(default_factory=list)
    certificates: list[tuple[str, str | None, str | None]] = field(default_factory=list)  # (name, was, now)
    enabled: list[tuple[str, bool]] = field(default_factory=list)  # (name, now)
    grants_added: list[tuple[str, GrantRow]] = field(default_factory=list)
    grants_removed: list[tuple[str, GrantRow]] = field(default_factory=list)


def _target_fingerprint(w: WantedManager, current: str | None, *, merge: bool, known: bool) -> str | None:
    """The certificate ``w`` is bound to after the import: a manager the registry holds
    keeps its own when the file leaves the key out, or (on a merge) says null."""
    if known and (not w.fingerprint_given or (merge and w.fingerprint is None)):
        return current
    return w.fingerprint


def _check_one_manager_per_certificate(wanted: Mapping[str, WantedManager], target: Mapping[str, str | None]) -> None:
    owner: dict[str, str] = {}
    for name, fp in target.items():
        if fp is None:
            continue
        if fp in owner:
            kept = [n for n in (owner[fp], name) if not wanted[n].fingerprint_given]
            raise RegistryError(
                f"policy binds one certificate to managers {owner[fp]!r} and {name!r}"
                + (f" ({kept[0]!r} keeps its own: the file gives it no fingerprint_sha256)" if kept else ""))
        owner[fp] = name


_MANAGER_KEYS = {"name", "fingerprint_sha256", "enabled", "grants"}


def parse_policy(doc: object) -> dict[str, WantedManager]:
    """Validate a policy document (from YAML) completely; raise RegistryError on any fault."""
    if not isinstance(doc, Mapping):
        raise RegistryError("policy must be a mapping with 'version' and 'managers'")
    unknown = set(doc) - {"version", "managers"}
    if unknown:
        raise RegistryError(f"policy: unknown key(s) {', '.join(sorted(map(str, unknown)))}")
    version = doc.get("version")
    if type(version) is not int or version != POLICY_VERSION:  # not 1.0, nor true (== 1 in Python)
        raise RegistryError(f"policy: version must be {POLICY_VERSION}, got {version!r}")
    # only 'managers: []' is empty: an absent or null list (a file cut short after
    # 'managers:') or '{}' read as [] would remove every manager
    managers = doc.get("managers")
    if not isinstance(managers, list):
        found = _shape(managers) if "managers" in doc else "no 'managers' key"
        raise RegistryError(f"policy: 'managers' must be a list, got {found} "
                            "(write 'managers: []' for a policy with none)")
    out: dict[str, WantedManager] = {}
    for i, m in enumerate(managers):
        where = f"policy: managers[{i}]"
        if isinstance(m, Mapping) and isinstance(m.get("name"), str) and len(m["name"]) <= 64:
            where += f" ({m['name']})"  # the index counts from 0: the name says which one
        if not isinstance(m, Mapping):
            raise RegistryError(f"{where} must be a mapping")
        unknown = set(m) - _MANAGER_KEYS
        if unknown:
            raise RegistryError(f"{where}: unknown key(s) {', '.join(sorted(map(str, unknown)))}")
        try:
            name = validate_manager_name(m.get("name"))
            fp = m.get("fingerprint_sha256")
            fp = normalize_fingerprint(fp) if fp is not None else None
            fp_given = "fingerprint_sha256" in m
            enabled = m.get("enabled")  # absent: true, or on a merge the manager's own state
            if enabled is not None and not isinstance(enabled, bool):
                raise RegistryError(f"'enabled' must be true or false, got {enabled!r}")
            grants = _parse_grants({} if m.get("grants") is None else m["grants"])
        except RegistryError as exc:
            raise RegistryError(f"{where}: {exc}") from None
        if name in out:
            raise RegistryError(f"{where}: manager {name!r} listed twice")
        out[name] = WantedManager(name, fp, enabled, grants, fp_given)
    return out


def _shape(value: object) -> str:
    """How a YAML value reads, for an error that says what was found instead."""
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return f"a boolean ({value})".lower()
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, str):
        return f"a string ({value!r})" if len(value) <= 40 else "a string"
    if isinstance(value, int | float):
        return f"a number ({value})"
    return type(value).__name__


def _key_problem(item: object, keys: set[str]) -> str:
    """What is wrong with a grant's keys, said plainly: the missing and the unknown ones."""
    if not isinstance(item, Mapping):
        return f"is {_shape(item)}, not a mapping"
    missing = sorted(keys - set(item))
    unknown = sorted(map(str, set(item) - keys))
    said = ([f"lacks {', '.join(repr(k) for k in missing)}"] if missing else []) + \
        ([f"has the unknown key(s) {', '.join(repr(k) for k in unknown)}"] if unknown else [])
    return " and ".join(said)


def _parse_grants(grants: object) -> frozenset[GrantRow]:
    if not isinstance(grants, Mapping):
        raise RegistryError("'grants' must be a mapping of action to a list")
    rows = set()
    for action, items in grants.items():
        validate_action(action)
        key = grant_key(action)
        keys = {"node", key} if action in PARAM_ACTIONS else {"node", key, "type"}
        if not isinstance(items, list):
            raise RegistryError(f"grants.{action} must be a list")
        for j, item in enumerate(items):
            where = f"grants.{action}[{j}]"
            if not isinstance(item, Mapping) or set(item) != keys:
                raise RegistryError(f"{where} {_key_problem(item, keys)} (a {action} grant has exactly the keys "
                                    f"{', '.join(sorted(keys))})")
            try:
                rows.add(GrantRow.checked(action, item["node"], item[key], item.get("type")))
            except RegistryError as exc:
                raise RegistryError(f"{where}: {exc}") from None
    return frozenset(rows)
