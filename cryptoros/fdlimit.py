"""The process's descriptor limit, lifted for daemons that hold a connection per peer."""

from __future__ import annotations

import logging
import resource


def raise_descriptor_limit(ceiling: int = 1 << 20) -> None:
    """Lift the soft RLIMIT_NOFILE (often 1,024: systemd's default) to the hard one, at
    most ``ceiling``, so a daemon's own connection caps bind before the kernel's limit
    does (a stranger's half-open connections must meet the cap, not EMFILE)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = ceiling if hard == resource.RLIM_INFINITY else min(hard, ceiling)
    if soft != resource.RLIM_INFINITY and soft < want:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
        except (ValueError, OSError) as exc:  # pragma: no cover - a container that forbids it
            logging.getLogger(__name__).warning("could not raise the descriptor limit from %d: %s", soft, exc)


__all__ = ["raise_descriptor_limit"]
