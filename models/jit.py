"""numpy arrays into Dr.Jit without a kernel per memory address.

Dr.Jit maps a C-contiguous numpy array without copying it, and its LLVM backend
specializes a kernel on the alignment of every input it loads: ``align 64`` where the
data starts on a 64-byte boundary, ``align 1`` elsewhere. numpy's data is 16-byte
aligned (glibc's allocator), so whether an input is 64-byte aligned is chance, and
kernels that read k numpy arrays compile in up to 2^k variants, one per pattern met: the
large MLP's literal-weight kernel takes about a minute to compile each time on a cold
cache, so the variants multiply the export's measurement time several times over. :func:`to_drjit` copies into
a 64-byte aligned buffer first, so one kernel serves every call.
"""

from __future__ import annotations

import numpy as np

ALIGN = 64  # bytes


def aligned(a, dtype=np.float32) -> np.ndarray:
    """``a`` (flattened) as a C-contiguous ``dtype`` array whose data starts on a 64-byte boundary."""
    a = np.asarray(a, dtype)
    if a.flags.c_contiguous and a.ctypes.data % ALIGN == 0:
        return a.ravel()
    size = a.size
    item = np.dtype(dtype).itemsize
    buf = np.empty(size + ALIGN // item, dtype)
    k = (-buf.ctypes.data % ALIGN) // item
    out = buf[k: k + size]
    out[:] = a.ravel()
    return out


def to_drjit(Float, a, dtype=np.float32):
    """A Dr.Jit array of type ``Float`` (or ``UInt``, with ``dtype``) holding ``a``, from aligned memory."""
    return Float(aligned(a, dtype))
