"""Where the daemon's socket is, and whether a client may trust the one it finds there.

Whoever can write the directory a socket lives in can unlink the socket and bind their own in its
place, and then a client's `estop` goes to them. So the daemon binds only in a directory that it
(or root) owns and that nobody else can write (usmswitch.daemon.sockdir), and a client connects
only to a socket owned by itself or root, or to one in a directory placed by root (e.g. systemd's
/run/usmswitch) and owned by the socket's owner.

Pure standard library: both ends of the socket import it.
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
    "check_socket_owner",
    "client_socket_paths",
    "default_socket_path",
    "describe_path",
    "rig_socket_path",
    "user_text",
    "web_token_path",
]


class UntrustedSocketError(PermissionError):
    """A socket or its directory that someone else could have put there; the message says who and how."""


def user_text(uid: int) -> str:
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def _group(gid: int) -> str:
    try:
        return f"{grp.getgrgid(gid).gr_name} (gid {gid})"
    except KeyError:
        return f"gid {gid}"


def describe_path(path: Path, st: os.stat_result) -> str:
    mode = stat.S_IMODE(st.st_mode)
    return f"{path} (owner {user_text(st.st_uid)}, group {_group(st.st_gid)}, mode {mode:04o})"


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
        f"socket {describe_path(p, st)} belongs to another user and its directory is not a private one"
        f" placed by root: refusing to trust it (run the daemon as {user_text(me)}, or use the service's"
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
            f"the process listening on the socket runs as {user_text(uid)},"
            f" not as its owner {user_text(owner)}"
        )


# -- where the socket is -------------------------------------------------------------------------
SOCKET_NAME = "usmswitchd.sock"


def default_socket_path(env: Mapping[str, str] | None = None) -> Path:
    """Where the daemon listens: $RUNTIME_DIRECTORY (systemd), else $XDG_RUNTIME_DIR/usmswitch, else a
    per-user /tmp/usmswitch-<uid> (created 0700 and checked before use: usmswitch.daemon.sockdir)."""
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


def tcp_token_path(socket_path: str | os.PathLike[str]) -> Path:
    """The TCP token the daemon made because none was configured, beside the socket
    (`usmswitchd.sock` -> `usmswitchd.tcp-token`), mode 0640 and the socket's group."""
    p = Path(socket_path)
    return p.with_name(f"{p.stem}.tcp-token")


def weak_token(token: str, least: int = 16) -> str | None:
    """Why `token` is too weak to guard a TCP socket (None: it will do): shorter than `least`,
    white space at its ends or only, fewer than 8 different characters, or a shorter text repeated
    (`aaaaaaaaaaaaaaaa`, `passwordpassword` and 16 spaces were all taken)."""
    if len(token) < least:
        return f"{len(token)} characters is too short to resist guessing (>= {least})"
    if token != token.strip() or not token.strip():
        return "it begins or ends with white space"
    for size in range(1, len(token) // 2 + 1):
        if len(token) % size == 0 and token[:size] * (len(token) // size) == token:
            return f"it is {token[:size]!r} repeated"
    if len(set(token)) < 8:
        return f"it has {len(set(token))} different characters (>= 8)"
    return None


def web_token_path(socket_path: str | os.PathLike[str]) -> Path:
    """The browser panel's token beside the socket (`usmswitchd.sock` -> `usmswitchd.web-token`):
    mode 0640 and the socket's group, so whoever may use the socket may act from the panel."""
    p = Path(socket_path)
    return p.with_name(f"{p.stem}.web-token")
