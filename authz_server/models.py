"""The registry's tables (SQLAlchemy 2 typed ORM).

Following the CryptoROS paper's ERD: one ``manager`` (the paper's *user*) owns many
``publisher``, ``subscriber``, ``service`` and ``service_client`` rows, each a
``(node name, topic or service, data type)`` triple. Beside the policy the registry
keeps what the token issuer needs: RSA signing keys by ``kid``, revoked token ids, an
audit log of issued and refused tokens, a revocation serial that bumps whenever the
revocation feed changes, and the hash-chained record of every change made to the
registry (``registry_change``).

The schema is owned by the Alembic migrations in ``authz_server/migrations``; these
classes must match them (a test compares the two).
"""

from __future__ import annotations

from datetime import datetime
from typing import ClassVar

from sqlalchemy import (
    Boolean,
    DateTime,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, declared_attr, mapped_column, relationship

NAME_LEN = 256


class Base(DeclarativeBase):
    pass


class Manager(Base):
    """A robot team manager: the identity a client certificate is bound to."""

    __tablename__ = "manager"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(128), unique=True, nullable=False)
    #: lowercase hex SHA-256 of the DER client certificate
    cert_fingerprint: Mapped[str | None] = mapped_column(String(64), unique=True, nullable=True)
    #: the certificate this one renewed, still accepted until ``previous_until`` (Unix
    #: seconds): ``set-cert --overlap``, so a robot keeps its tokens until it reloads
    previous_fingerprint: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)
    previous_until: Mapped[int | None] = mapped_column(Integer, nullable=True)
    enabled: Mapped[bool] = mapped_column(Boolean, nullable=False, default=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), nullable=False)
    #: learning mode (``cryptoros-authz learn start``): the window, in Unix seconds
    learning_since: Mapped[int | None] = mapped_column(Integer, nullable=True)
    learning_until: Mapped[int | None] = mapped_column(Integer, nullable=True)

    publishers: Mapped[list[Publisher]] = relationship(
        back_populates="manager", cascade="all, delete-orphan", order_by="Publisher.id"
    )
    subscribers: Mapped[list[Subscriber]] = relationship(
        back_populates="manager", cascade="all, delete-orphan", order_by="Subscriber.id"
    )
    services: Mapped[list[Service]] = relationship(
        back_populates="manager", cascade="all, delete-orphan", order_by="Service.id"
    )
    service_clients: Mapped[list[ServiceClient]] = relationship(
        back_populates="manager", cascade="all, delete-orphan", order_by="ServiceClient.id"
    )
    param_readers: Mapped[list[ParamReader]] = relationship(
        back_populates="manager", cascade="all, delete-orphan", order_by="ParamReader.id"
    )
    param_writers: Mapped[list[ParamWriter]] = relationship(
        back_populates="manager", cascade="all, delete-orphan", order_by="ParamWriter.id"
    )


class _Grant:
    """A grant row, the columns every grant table has in this order: ``id``,
    ``manager_id``, ``name`` (a node name or pattern), the table's own target column
    (``topic``, ``service`` or ``namespace``: :attr:`TARGET`), ``data_type``; unique on
    ``(manager_id, name, <target>, data_type)`` as ``uq_<table>``. :attr:`RELATION` is
    the list on :class:`Manager` the row belongs to."""

    TARGET: ClassVar[str]
    RELATION: ClassVar[str]

    id: Mapped[int] = mapped_column(Integer, primary_key=True, sort_order=-3)
    manager_id: Mapped[int] = mapped_column(ForeignKey("manager.id", ondelete="CASCADE"), nullable=False, index=True,
                                            sort_order=-2)
    name: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False, sort_order=-1)
    data_type: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False, sort_order=1)

    @declared_attr.directive
    def __table_args__(cls) -> tuple:
        return (UniqueConstraint("manager_id", "name", cls.TARGET, "data_type", name=f"uq_{cls.__tablename__}"),)

    @declared_attr
    def manager(cls) -> Mapped[Manager]:
        return relationship(back_populates=cls.RELATION)


class Publisher(_Grant, Base):
    __tablename__ = "publisher"
    TARGET, RELATION = "topic", "publishers"
    topic: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)


class Subscriber(_Grant, Base):
    __tablename__ = "subscriber"
    TARGET, RELATION = "topic", "subscribers"
    topic: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)


class Service(_Grant, Base):
    __tablename__ = "service"
    TARGET, RELATION = "service", "services"
    service: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)


class ServiceClient(_Grant, Base):
    __tablename__ = "service_client"
    TARGET, RELATION = "service", "service_clients"
    service: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)


class ParamReader(_Grant, Base):
    """``name`` (a node) may read the parameters in ``namespace`` (data_type is ``param``)."""

    __tablename__ = "param_reader"
    TARGET, RELATION = "namespace", "param_readers"
    namespace: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)


class ParamWriter(_Grant, Base):
    """``name`` (a node) may read and write the parameters in ``namespace``."""

    __tablename__ = "param_writer"
    TARGET, RELATION = "namespace", "param_writers"
    namespace: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)


#: action -> (ORM class, name of the topic/service column, relationship on Manager)
GRANT_TABLES: dict[str, tuple[type[_Grant], str, str]] = {
    action: (cls, cls.TARGET, cls.RELATION)
    for action, cls in (("publish", Publisher), ("subscribe", Subscriber), ("serve", Service),
                        ("call", ServiceClient), ("read_param", ParamReader), ("write_param", ParamWriter))
}


class Observation(Base):
    """What a manager's interceptors saw its nodes do (``POST /observations``): a request a
    grant allowed (``allowed``), or one only learning mode let through. One row per
    (manager, allowed, action, node, name, type); ``data_type`` is ``""`` when the
    request did not tell it (a service registration)."""

    __tablename__ = "observation"
    __table_args__ = (UniqueConstraint("manager_id", "allowed", "action", "node", "name", "data_type",
                                       name="uq_observation"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    manager_id: Mapped[int] = mapped_column(ForeignKey("manager.id", ondelete="CASCADE"), nullable=False, index=True)
    allowed: Mapped[bool] = mapped_column(Boolean, nullable=False)
    action: Mapped[str] = mapped_column(String(16), nullable=False)
    node: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)
    name: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)
    data_type: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)
    count: Mapped[int] = mapped_column(Integer, nullable=False)
    first_seen: Mapped[int] = mapped_column(Integer, nullable=False)
    last_seen: Mapped[int] = mapped_column(Integer, nullable=False, index=True)


class RevokedToken(Base):
    __tablename__ = "revoked_token"

    jti: Mapped[str] = mapped_column(String(64), primary_key=True)
    #: when the token expires anyway; the feed stops listing it after that
    expires_at: Mapped[int] = mapped_column(Integer, nullable=False, index=True)
    revoked_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), nullable=False)
    reason: Mapped[str] = mapped_column(String(256), nullable=False, default="")


class AuditLog(Base):
    """One row per token issued or refused."""

    __tablename__ = "audit_log"
    __table_args__ = (Index("ix_audit_log_kid_expires", "kid", "expires_at"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    at: Mapped[datetime] = mapped_column(DateTime(timezone=True), nullable=False, index=True)
    event: Mapped[str] = mapped_column(String(16), nullable=False)  # "issued" | "denied"
    manager: Mapped[str | None] = mapped_column(String(128), nullable=True, index=True)
    cert_fingerprint: Mapped[str | None] = mapped_column(String(64), nullable=True)
    remote: Mapped[str | None] = mapped_column(String(128), nullable=True)
    reason: Mapped[str] = mapped_column(String(256), nullable=False, default="")
    jti: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)
    kid: Mapped[str | None] = mapped_column(String(64), nullable=True)
    expires_at: Mapped[int | None] = mapped_column(Integer, nullable=True)


class RegistryChange(Base):
    """One change to the registry (a manager, its certificate or grants, a signing key,
    a revoked token): who made it, from where, with which command, and what it changed.

    Written in the transaction of the change itself. Rows form a hash chain: ``hash``
    is the SHA-256 of the row's canonical content, ``prev_hash`` included
    (:mod:`authz_server.changes`), so a row deleted, inserted or edited is detected.
    ``seq`` numbers the rows 1, 2, ...; the registry_state counter ``change_chain``
    holds the last one (a row cut from the end is detected too)."""

    __tablename__ = "registry_change"

    seq: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    at: Mapped[datetime] = mapped_column(DateTime(timezone=True), nullable=False, index=True)
    os_user: Mapped[str] = mapped_column(String(128), nullable=False)
    host: Mapped[str] = mapped_column(String(255), nullable=False)
    command: Mapped[str] = mapped_column(Text, nullable=False)
    target: Mapped[str] = mapped_column(String(NAME_LEN), nullable=False)
    #: JSON (canonical: sorted keys, no spaces) of what the change replaced, or null
    before: Mapped[str | None] = mapped_column(Text, nullable=True)
    #: JSON of what the change put in its place, or null
    after: Mapped[str | None] = mapped_column(Text, nullable=True)
    prev_hash: Mapped[str] = mapped_column(String(64), nullable=False)
    hash: Mapped[str] = mapped_column(String(64), nullable=False)


class SigningKey(Base):
    """An RSA key the issuer signs with. Exactly one is ``active``; retired keys stay
    published in the JWKS while a token they signed may still be valid."""

    __tablename__ = "signing_key"

    kid: Mapped[str] = mapped_column(String(64), primary_key=True)
    algorithm: Mapped[str] = mapped_column(String(16), nullable=False, default="RS256")
    private_pem: Mapped[bytes] = mapped_column(LargeBinary, nullable=False)
    public_pem: Mapped[str] = mapped_column(Text, nullable=False)
    encrypted: Mapped[bool] = mapped_column(Boolean, nullable=False)
    active: Mapped[bool] = mapped_column(Boolean, nullable=False, default=False)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), nullable=False)
    retired_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


class RegistryState(Base):
    """Small named counters (``revocation_serial``, ``registry_version``, ``change_chain``)."""

    __tablename__ = "registry_state"

    key: Mapped[str] = mapped_column(String(64), primary_key=True)
    value: Mapped[int] = mapped_column(Integer, nullable=False, default=0)
