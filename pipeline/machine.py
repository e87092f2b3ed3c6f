"""What the machine offers, asked once where a check needs it."""

from __future__ import annotations

import os


def memory_bytes() -> int:
    """Physical memory in bytes (16 GiB where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 16 * 2**30


# A single piece of work may take at most this share of the machine's memory: the rest is
# the interpreter, Mitsuba, the OS and whatever else the user runs.
MEMORY_SHARE = 0.5


def check_memory(need: float, what: str, fix: str) -> None:
    """Refuse, before it starts, work that needs ``need`` bytes, more than
    :data:`MEMORY_SHARE` of this machine's memory: ``"{what}, ~N GiB, more than half of this
    machine's M GiB: {fix}"``."""
    have = memory_bytes()
    if need > MEMORY_SHARE * have:
        raise ValueError(f"{what}, ~{need / 2**30:.1f} GiB, more than half of this machine's {have / 2**30:.0f} GiB: "
                         f"{fix}")
