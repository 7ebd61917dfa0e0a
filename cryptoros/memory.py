"""Process-wide memory settings (no event loop, no I/O but the C library call)."""

from __future__ import annotations


def tune_malloc(threshold: int = 16 << 20) -> bool:
    """Keep glibc from mmap-ing (and page-faulting) every buffer of 128 KiB or more:
    large messages then reuse heap memory (+30 to 100 % on 1 MB messages; docs/ros1-wire.md)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_mmap_threshold, m_trim_threshold = -3, -1
        return bool(libc.mallopt(m_mmap_threshold, threshold)) and bool(libc.mallopt(m_trim_threshold, 4 * threshold))
    except (OSError, AttributeError):
        return False


__all__ = ["tune_malloc"]
