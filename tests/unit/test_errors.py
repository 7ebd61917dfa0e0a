"""Every exception class of cryptoros/, certs/ and authz_server/ is a CryptorosError."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

from cryptoros.errors import CryptorosError

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
