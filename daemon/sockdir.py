"""The socket's directory on the daemon's side: created private, and checked before binding in it.

Whoever can write the directory a socket lives in can unlink the socket and bind their own in its
place, and then a client's `estop` goes to them. So the daemon binds only in a directory that it
(or root) owns and that nobody else can write, creating a missing one mode 0700. The client's half
(where the socket is, whether to trust it) is usmswitch.protocol.sockets.
"""

from __future__ import annotations

import grp
import os
import stat
from pathlib import Path

from usmswitch.protocol.sockets import UntrustedSocketError, describe_path, user_text

__all__ = ["check_private_dir", "ensure_private_dir", "prepare_socket_dir"]


def _gid(group: str | None) -> int | None:
    if not group:
        return None
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise UntrustedSocketError(f"socket group {group!r} does not exist") from None


def ensure_private_dir(path: str | os.PathLike[str], group: str | None = None) -> Path:
    """Create `path` if missing: mode 0700, or 0750 and the group `group` when one is given.

    Missing parents are created as the umask makes them; an existing directory is left as it is
    (`check_private_dir` says whether it may be used).
    """
    p = Path(path)
    gid = _gid(group)
    mode = 0o750 if gid is not None else 0o700
    p.parent.mkdir(parents=True, exist_ok=True)
    try:
        p.mkdir(mode=mode)
    except FileExistsError:
        return p
    # mkdir's mode went through the umask: set it exactly, and the group before anyone can look.
    if gid is not None:
        os.chown(p, -1, gid)
    os.chmod(p, mode)
    return p


def check_private_dir(path: str | os.PathLike[str], group: str | None = None) -> None:
    """Refuse a directory another user could put a socket in; returns quietly when it is private.

    It must be a directory owned by this process's user or root, and writable by nobody else:
    no write bit for others, and a group write bit only when the directory is ours and its group is
    the configured `group` (systemd's RuntimeDirectory with RuntimeDirectoryMode=0770).
    A symlink is followed only when it is itself owned by us or root.
    """
    p = Path(path)
    me = os.geteuid()
    try:
        lst = os.lstat(p)
    except FileNotFoundError:
        raise UntrustedSocketError(f"socket directory {p} does not exist") from None
    if stat.S_ISLNK(lst.st_mode):
        if lst.st_uid not in (me, 0):
            raise UntrustedSocketError(
                f"socket directory {p} is a symlink owned by {user_text(lst.st_uid)}: another user can"
                " point it anywhere; use a directory of your own (socket.path)"
            )
        lst = os.stat(p)
    if not stat.S_ISDIR(lst.st_mode):
        raise UntrustedSocketError(f"socket directory {p} is not a directory")
    where = describe_path(p, lst)
    if lst.st_uid not in (me, 0):
        raise UntrustedSocketError(
            f"socket directory {where} belongs to another user, who could swap the socket;"
            f" remove it or set socket.path to a directory owned by {user_text(me)}"
        )
    mode = stat.S_IMODE(lst.st_mode)
    if mode & stat.S_IWOTH:
        raise UntrustedSocketError(
            f"socket directory {where} is writable by others, who could swap the socket;"
            " chmod o-w it or set socket.path to a private directory"
        )
    if mode & stat.S_IWGRP:
        gid = _gid(group)
        if gid is None or lst.st_gid != gid or lst.st_uid != me:
            allowed = f"group {group!r}" if group else "no group (socket.group is unset)"
            raise UntrustedSocketError(
                f"socket directory {where} is writable by its group, and the config allows {allowed};"
                " chmod g-w it or set socket.group to the directory's group"
            )


def prepare_socket_dir(path: str | os.PathLike[str], group: str | None = None) -> Path:
    """Before binding the socket at `path`: its directory created private if missing, then checked."""
    parent = Path(path).parent
    ensure_private_dir(parent, group)
    check_private_dir(parent, group)
    return parent
