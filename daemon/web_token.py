"""The browser panel's token (and the TCP socket's when none is configured): made at each start,
kept in a file beside the socket that only the socket's group may read (mode 0640), removed at stop.
Whoever may use the socket may act from the panel, and nobody else (Jupyter's tokened URL, with the
socket's group as the audience)."""

from __future__ import annotations

import contextlib
import grp
import os
import secrets
from pathlib import Path

TOKEN_MODE = 0o640


class TokenFile:
    """The token and its file; `stop()` removes the file (an RpcServer companion)."""

    def __init__(self, path: str | os.PathLike[str], group: str | None = None) -> None:
        self.path = Path(path)
        self.token = secrets.token_urlsafe(32)
        self._ino: int | None = None
        gid = None if not group else grp.getgrnam(group).gr_gid
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}")
        tmp.unlink(missing_ok=True)
        # Created 0600 under the umask, group set, then 0640: no instant where another user reads it.
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
        try:
            if gid is not None:
                os.fchown(fd, -1, gid)
            os.fchmod(fd, TOKEN_MODE)
            os.write(fd, (self.token + "\n").encode())
        finally:
            os.close(fd)
        os.replace(tmp, self.path)  # atomic: a reader sees the old token or the new, never half
        self._ino = os.stat(self.path).st_ino

    def stop(self) -> None:
        """Remove the file, unless a newer daemon has replaced it since."""
        with contextlib.suppress(OSError):
            if self._ino is not None and os.stat(self.path).st_ino == self._ino:
                self.path.unlink()
        self._ino = None
