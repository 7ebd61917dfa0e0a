"""Every exception class of cryptoros/, certs/ and authz_server/ is a CryptorosError."""

from __future__ import annotations

import ast
import asyncio
import importlib
import ssl
from pathlib import Path

from cryptoros.errors import (
    PEER_FAILURES,
    ConfigError,
    CryptorosError,
    PolicyDenied,
    Refusal,
    RemoteProtocolError,
    TokenError,
)

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("cryptoros", "certs", "authz_server")
#: Outside CryptorosError on purpose: both modules also run in the rclpy bridge child
#: (the ROS 2 venv's python), which imports framing.py on its own, without the cryptoros
#: package; the ROS 2 role translates FrameError to RemoteProtocolError at the boundary.
BRIDGE_CHILD_ERRORS = {"cryptoros.ros2.framing.FrameError", "cryptoros.ros2.bridge_node.NoAnswer"}
#: Modules that need an interpreter other than ours (system rospy, rclpy) to import.
SKIP_IMPORT = ("cryptoros.ros2.bridge_node", "cryptoros.bench.ros1_nodes", "cryptoros.demo.nodes")


def _exception_classes() -> list[str]:
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef) and any(
                    isinstance(b, (ast.Name, ast.Attribute)) and ast.unparse(b).endswith(("Error", "Exception"))
                    for b in node.bases
                ):
                    found.append(f"{module}.{node.name}")
    return found


def test_every_exception_class_is_a_cryptoros_error():
    wrong = []
    for qualname in _exception_classes():
        module, _, name = qualname.rpartition(".")
        if qualname in BRIDGE_CHILD_ERRORS or module.startswith(SKIP_IMPORT):
            continue
        cls = getattr(importlib.import_module(module), name)
        if not issubclass(cls, CryptorosError):
            wrong.append(qualname)
    assert not wrong, f"exception classes outside CryptorosError: {wrong}"


def test_every_error_carries_a_reason_and_a_detail():
    """One base carries both: a refusal is raised with its code first, any other error
    with a message, which is its detail (its class's default reason, else its class name,
    the reason)."""
    denied = PolicyDenied("not_granted", "no grant for /chatter")
    assert (denied.reason, denied.detail, str(denied)) == ("not_granted", "no grant for /chatter",
                                                           "not_granted: no grant for /chatter")
    bare = TokenError("expired")
    assert (bare.reason, bare.detail, str(bare)) == ("expired", "", "expired")
    assert isinstance(denied, Refusal) and isinstance(bare, Refusal)
    config = ConfigError("cannot read /etc/x.toml")
    assert (config.reason, config.detail, str(config)) == ("ConfigError", "cannot read /etc/x.toml",
                                                           "cannot read /etc/x.toml")
    # a protocol error's reason is a code (a metric label), not its class name
    assert RemoteProtocolError().reason == "malformed" and str(RemoteProtocolError()) == ""
    assert RemoteProtocolError("bad frame").reason == "malformed"
    assert RemoteProtocolError("bad frame", reason="oversized").reason == "oversized"


def test_peer_failures_cover_what_a_peer_or_its_socket_raises():
    for exc in (PolicyDenied("rate_limited"), ConnectionResetError(), asyncio.TimeoutError(),
                ssl.SSLError(1, "bad certificate"), OSError(113, "no route to host")):
        assert isinstance(exc, PEER_FAILURES), exc
    assert not isinstance(ValueError("a bug of ours"), PEER_FAILURES)
