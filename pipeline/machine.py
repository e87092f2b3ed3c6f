"""What the machine offers, asked once where a check needs it."""

from __future__ import annotations

import os


def memory_bytes() -> int:
    """Physical memory in bytes (16 GiB where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 16 * 2**30
