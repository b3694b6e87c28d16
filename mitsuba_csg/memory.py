"""The memory a job will need, estimated from its counts, against what the machine has free:
work that cannot fit is refused up front with the numbers, not ended by a MemoryError (or
the kernel's OOM killer) halfway through."""
from __future__ import annotations

from .errors import ModelError

# Measured peaks (docs/limits.md): lowering, optimizing and uploading a model costs about
# 1.5 kB per primitive beyond the model itself (0.4 kB per primitive); reading native JSON
# about 6 bytes per byte of the file to parse it and 1.2 kB per node to build the model (a
# 24 MB file of 300000 transformed spheres peaked at 353 MB).
BYTES_PER_PRIMITIVE = 2000
BYTES_PER_JSON_BYTE = 6
BYTES_PER_JSON_NODE = 1200


def available_bytes() -> int | None:
    """Memory the system can give without swapping (Linux's MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def require(needed: float, what: str) -> None:
    """Refuse `what` when it needs more than the machine has available."""
    available = available_bytes()
    if available is not None and needed > available:
        raise ModelError(f"{what} needs about {_size(needed)} of memory, and {_size(available)} are available; "
                         f"use a machine with more memory or a smaller model")


def _size(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"
