"""What every file reader shares: the error type, and reading a file with a size limit."""
from __future__ import annotations

import os
import stat

from ..errors import ModelError


class FormatError(ModelError):
    """A model file that cannot be read: the message starts with the source and the place in it."""


def check_regular_file(info: os.stat_result, source: str) -> None:
    """Refuse what is not a plain file before opening it: reading a FIFO or a device blocks
    or never ends."""
    if stat.S_ISDIR(info.st_mode):
        raise IsADirectoryError
    if not stat.S_ISREG(info.st_mode):
        raise FormatError(f"{source}: not a regular file (a FIFO, device or socket), so it is not read")


def read_model_bytes(path, max_bytes: int | None = None) -> tuple[bytes, str]:
    """(contents, name for messages) of a model file, or one FormatError saying why not.

    Shared by every loader, so a missing file or a directory reads the same in all formats.
    """
    source = os.fsdecode(path) if isinstance(path, (str, bytes, os.PathLike)) else repr(path)
    try:
        info = os.stat(path)
        check_regular_file(info, source)
        if max_bytes is not None and info.st_size > max_bytes:
            raise FormatError(f"{source}: {info.st_size} bytes is larger than the limit of {max_bytes}")
        with open(path, "rb") as f:
            raw = f.read() if max_bytes is None else f.read(max_bytes + 1)
    except FormatError:
        raise
    except FileNotFoundError:
        raise FormatError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise FormatError(f"{source}: is a directory, not a model file") from None
    except (OSError, TypeError, ValueError) as e:
        raise FormatError(f"{source}: cannot read the file ({getattr(e, 'strerror', None) or e})") from None
    return raw, source
