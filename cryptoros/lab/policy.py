"""The registry policy of a lab network (``cryptoros-authz import``), written from
Python values.

The lab, the benches, the demo and the tests each describe who may do what as
``{manager: {action: [(node, name, type), ...]}}``; :func:`policy_yaml` writes the YAML
the registry imports (docs/authz.md). ``name`` is a topic (publish, subscribe), a
service (serve, call) or a parameter namespace (read_param, write_param: type None).
Without ``fingerprints`` each manager's certificate fingerprint is a ``{manager}``
placeholder and every other brace is doubled: the template
:func:`cryptoros.lab.network.lab_network` fills with ``str.format``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

#: (node name or pattern, topic / service / namespace, type or None)
Grant = tuple[str, str, "str | None"]
Managers = Mapping[str, Mapping[str, Sequence[Grant]]]


def _target_key(action: str) -> str:
    if action in ("publish", "subscribe"):
        return "topic"
    return "namespace" if action in ("read_param", "write_param") else "service"


def _scalar(text: str) -> str:
    # a plain YAML scalar may not start with '*' (an alias): patterns are quoted
    return f"'{text}'" if "*" in text else text


def policy_yaml(managers: Managers, *, fingerprints: Mapping[str, str] | None = None) -> str:
    """The policy YAML of ``managers`` (in their order); see the module docstring."""
    template = fingerprints is None
    lines = ["version: 1", "managers:"]
    for name, grants in managers.items():
        fingerprint = f"{{{name}}}" if fingerprints is None else fingerprints[name]
        lines += [f"- name: {name}", f"  fingerprint_sha256: {fingerprint}"]
        if grants:
            lines.append("  grants:")
        for action, rows in grants.items():
            lines.append(f"    {action}:")
            for node, target, type_name in rows:
                body = f"node: {_scalar(node)}, {_target_key(action)}: {target}"
                body += f", type: {type_name}" if type_name is not None else ""
                lines.append(f"    - {{{{{body}}}}}" if template else f"    - {{{body}}}")
    return "\n".join(lines) + "\n"


__all__ = ["Grant", "policy_yaml"]
