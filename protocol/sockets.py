"""The Unix socket's directory and file: private, and checked before anyone trusts them.

Whoever can write the directory a socket lives in can unlink the socket and bind their own in its
place, and then a client's `estop` goes to them. So the daemon binds only in a directory that it
(or root) owns and that nobody else can write, creating a missing one mode 0700, and a client
connects only to a socket owned by itself or root, or to one in a directory placed by root (e.g.
systemd's /run/usmswitch) and owned by the socket's owner.

Pure standard library and nothing of the daemon's runtime: the client imports it too.
"""

from __future__ import annotations

import grp
import os
import pwd
import socket
import stat
import struct
from collections.abc import Mapping
from pathlib import Path

__all__ = [
    "UntrustedSocketError",
    "check_peer",
    "check_private_dir",
    "check_socket_owner",
    "ensure_private_dir",
    "prepare_socket_dir",
    "rig_socket_path",
]


class UntrustedSocketError(PermissionError):
    """A socket or its directory that someone else could have put there; the message says who and how."""


def _user(uid: int) -> str:
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def _group(gid: int) -> str:
    try:
        return f"{grp.getgrgid(gid).gr_name} (gid {gid})"
    except KeyError:
        return f"gid {gid}"


def _describe(path: Path, st: os.stat_result) -> str:
    return (
        f"{path} (owner {_user(st.st_uid)}, group {_group(st.st_gid)}, mode {stat.S_IMODE(st.st_mode):04o})"
    )


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
                f"socket directory {p} is a symlink owned by {_user(lst.st_uid)}: another user can"
                " point it anywhere; use a directory of your own (socket.path)"
            )
        lst = os.stat(p)
    if not stat.S_ISDIR(lst.st_mode):
        raise UntrustedSocketError(f"socket directory {p} is not a directory")
    where = _describe(p, lst)
    if lst.st_uid not in (me, 0):
        raise UntrustedSocketError(
            f"socket directory {where} belongs to another user, who could swap the socket;"
            f" remove it or set socket.path to a directory owned by {_user(me)}"
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


def _placed_by_root(directory: Path, owner: int) -> bool:
    """A directory owned by `owner`, writable by nobody else, in a parent only root can write."""
    try:
        st = os.stat(directory)
        up = os.stat(directory.parent)
    except OSError:
        return False
    if st.st_uid != owner or stat.S_IMODE(st.st_mode) & (stat.S_IWOTH | stat.S_IWGRP):
        return False
    return up.st_uid == 0 and not stat.S_IMODE(up.st_mode) & (stat.S_IWOTH | stat.S_IWGRP)


def check_socket_owner(path: str | os.PathLike[str]) -> int:
    """Before connecting: the socket at `path` must be trustworthy. Returns the uid that owns it.

    Trusted: a socket owned by this user or root; or one owned by the user that owns its
    directory when that directory cannot be written by anyone else and sits in a directory only
    root can write (systemd's /run/usmswitch for the service user). A missing path raises
    FileNotFoundError as connect() would.
    """
    p = Path(path)
    st = os.lstat(p)
    if not stat.S_ISSOCK(st.st_mode):
        raise UntrustedSocketError(f"{p} is not a socket")
    me = os.geteuid()
    if st.st_uid in (me, 0) or _placed_by_root(p.parent, st.st_uid):
        return st.st_uid
    raise UntrustedSocketError(
        f"socket {_describe(p, st)} belongs to another user and its directory is not a private one"
        f" placed by root: refusing to trust it (run the daemon as {_user(me)}, or use the service's"
        " /run/usmswitch socket)"
    )


def check_peer(sock: socket.socket, owner: int) -> None:
    """After connecting: the process listening must run as this user, root, or the socket's owner.

    Closes the gap between checking the file and connecting (SO_PEERCRED, Linux); elsewhere a no-op.
    """
    opt = getattr(socket, "SO_PEERCRED", None)
    if opt is None:
        return
    _pid, uid, _ = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, opt, struct.calcsize("3i")))
    if uid not in (os.geteuid(), 0, owner):
        raise UntrustedSocketError(
            f"the process listening on the socket runs as {_user(uid)}, not as its owner {_user(owner)}"
        )


# -- where the socket is -------------------------------------------------------------------------
SOCKET_NAME = "usmswitchd.sock"


def default_socket_path(env: Mapping[str, str] | None = None) -> Path:
    """Where the daemon listens: $RUNTIME_DIRECTORY (systemd), else $XDG_RUNTIME_DIR/usmswitch, else a
    per-user /tmp/usmswitch-<uid> (created 0700 and checked before use: daemon/sockdir.py)."""
    env = os.environ if env is None else env
    if env.get("RUNTIME_DIRECTORY"):
        return Path(env["RUNTIME_DIRECTORY"].split(":")[0]) / SOCKET_NAME
    if env.get("XDG_RUNTIME_DIR"):
        return Path(env["XDG_RUNTIME_DIR"]) / "usmswitch" / SOCKET_NAME
    return Path(f"/tmp/usmswitch-{os.getuid()}") / SOCKET_NAME


#: Where the services put their sockets: /run/usmswitch for the one-rig unit, /run/usmswitch/<rig>
#: for each instance of the template unit usmswitchd@<rig>.service.
SERVICE_RUNTIME_DIR = Path("/run/usmswitch")


def rig_socket_path(rig: str) -> Path:
    """The socket of the service instance usmswitchd@<rig> (systemd/usmswitchd@.service)."""
    if not rig or "/" in rig or rig.startswith(".") or not rig.isprintable():
        raise ValueError(f"rig name {rig!r}: expected a name like 'rigA' (no '/', not starting with '.')")
    return SERVICE_RUNTIME_DIR / rig / SOCKET_NAME


def client_socket_paths(env: Mapping[str, str] | None = None) -> list[Path]:
    """Where a client looks for the daemon, in order: $USMSWITCH_SOCKET, the instance of rig
    $USMSWITCH_RIG, this user's daemon, the one-rig service's."""
    env = os.environ if env is None else env
    paths = [Path(env["USMSWITCH_SOCKET"])] if env.get("USMSWITCH_SOCKET") else []
    if env.get("USMSWITCH_RIG"):
        paths.append(rig_socket_path(env["USMSWITCH_RIG"]))
    paths.append(default_socket_path(env))
    paths.append(SERVICE_RUNTIME_DIR / SOCKET_NAME)
    return list(dict.fromkeys(paths))
