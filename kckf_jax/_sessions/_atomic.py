"""Files that appear whole or not at all: every file a command writes (estimates, sessions,
parameters, checkpoints, figures, the exported step) goes through ``atomic_write``.

Written beside the target under a hidden temporary name, flushed to disk, then renamed over it
(``os.replace``, atomic on POSIX and Windows): a run that is killed or fails while writing
leaves the previous file byte for byte as it was, and no partial file that would still parse.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterator
from typing import IO


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **open_kwargs) -> Iterator[IO]:
    """Open ``path`` for writing (``mode`` ``"w"`` or ``"wb"``, ``open_kwargs`` as ``open``'s)
    so that it is replaced only when the ``with`` block ends without an exception.

    The new file keeps the old one's permissions (a new one gets ``0o644``); the folder must
    exist.

    Example:
        >>> import os, tempfile
        >>> p = os.path.join(tempfile.mkdtemp(), "a.txt")
        >>> with atomic_write(p) as f:
        ...     _ = f.write("whole")
        >>> open(p).read()
        'whole'
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".part",
                               dir=folder)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        try:
            keep = stat.S_IMODE(os.stat(path).st_mode)
        except FileNotFoundError:
            keep = 0o644
        os.chmod(tmp, keep)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
