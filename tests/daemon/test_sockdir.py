"""The socket's directory and file: created private, refused when another user could swap the socket.

Real directories, real chown to another uid (root only), real listening sockets.
"""

from __future__ import annotations

import grp
import os
import socket
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from usmswitch.client import Client, UntrustedSocketError
from usmswitch.daemon.sockdir import check_private_dir, ensure_private_dir, prepare_socket_dir
from usmswitch.protocol.sockets import check_socket_owner

NOBODY = 65534
root_only = pytest.mark.skipif(os.geteuid() != 0, reason="chown to another uid needs root")


def mode(p: Path) -> int:
    return stat.S_IMODE(os.lstat(p).st_mode)


def listening(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.listen()
    return s


def a_group() -> str:
    """A group this process's user may chown to (its own primary group)."""
    return grp.getgrgid(os.getegid()).gr_name


def test_a_missing_directory_is_created_private(tmp_path: Path):
    old = os.umask(0o022)
    try:
        d = prepare_socket_dir(tmp_path / "run" / "usmswitch" / "usmswitchd.sock")
        assert d == tmp_path / "run" / "usmswitch" and mode(d) == 0o700
        g = ensure_private_dir(tmp_path / "grouped", a_group())
        assert mode(g) == 0o750 and os.stat(g).st_gid == os.getegid()
        # An existing directory is left as it is: only checked.
        (tmp_path / "open").mkdir(mode=0o755)
        ensure_private_dir(tmp_path / "open")
        assert mode(tmp_path / "open") == 0o755
        check_private_dir(tmp_path / "open")  # 0755: nobody else can write it
    finally:
        os.umask(old)


@pytest.mark.parametrize("bad_mode", [0o777, 0o1777, 0o702, 0o770])
def test_a_directory_others_or_the_group_can_write_is_refused(tmp_path: Path, bad_mode: int):
    d = tmp_path / "sockdir"
    d.mkdir()
    os.chmod(d, bad_mode)
    with pytest.raises(UntrustedSocketError) as info:
        prepare_socket_dir(d / "usmswitchd.sock")
    msg = str(info.value)
    assert str(d) in msg and f"mode {bad_mode & 0o7777:04o}" in msg and "owner" in msg


def test_a_group_writable_directory_of_the_configured_group_is_accepted(tmp_path: Path):
    # systemd's RuntimeDirectory=usmswitch with RuntimeDirectoryMode=0770 and socket.group set.
    d = tmp_path / "run"
    d.mkdir()
    os.chmod(d, 0o770)
    check_private_dir(d, a_group())
    with pytest.raises(UntrustedSocketError, match="writable by its group"):
        check_private_dir(d)  # the same directory without a configured group


@root_only
def test_a_directory_owned_by_another_user_is_refused_naming_it(tmp_path: Path):
    d = tmp_path / "usmswitch-0"
    d.mkdir(mode=0o700)
    os.chown(d, NOBODY, NOBODY)
    with pytest.raises(UntrustedSocketError) as info:
        prepare_socket_dir(d / "usmswitchd.sock")
    msg = str(info.value)
    assert str(d) in msg and f"uid {NOBODY}" in msg and "another user" in msg
    # A symlink another user owns is refused as well, wherever it points.
    link = tmp_path / "link"
    link.symlink_to(tmp_path)
    os.lchown(link, NOBODY, NOBODY)
    with pytest.raises(UntrustedSocketError, match="symlink owned by"):
        check_private_dir(link)


@root_only
def test_the_client_refuses_a_socket_owned_by_another_user(tmp_path: Path):
    d = tmp_path / "shared"
    d.mkdir()
    os.chmod(d, 0o1777)  # like /tmp: anyone could have put the socket here
    path = d / "usmswitchd.sock"
    srv = listening(path)
    try:
        os.chown(path, NOBODY, NOBODY)
        with pytest.raises(UntrustedSocketError) as info:
            Client(str(path), timeout=1)
        assert str(path) in str(info.value) and f"uid {NOBODY}" in str(info.value)
        os.chown(path, os.geteuid(), os.getegid())
        assert check_socket_owner(path) == os.geteuid()
    finally:
        srv.close()


@root_only
def test_the_client_trusts_the_service_user_s_socket_in_a_directory_root_placed(tmp_path: Path):
    # /run (root, 0755) / usmswitch (the service user, 0750) / usmswitchd.sock (the service user).
    run = tmp_path / "run"
    run.mkdir(mode=0o755)
    d = run / "usmswitch"
    d.mkdir(mode=0o750)
    path = d / "usmswitchd.sock"
    srv = listening(path)
    try:
        os.chown(path, NOBODY, NOBODY)
        os.chown(d, NOBODY, NOBODY)
        assert check_socket_owner(path) == NOBODY
        # The same directory made writable by others is no longer proof of anything.
        os.chmod(d, 0o757)
        with pytest.raises(UntrustedSocketError):
            check_socket_owner(path)
    finally:
        srv.close()


SWAPPER = textwrap.dedent(
    """
    import os, socket, sys
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(sys.argv[1])          # the file is created as root: it passes the owner check
    os.setgid({uid}); os.setuid({uid})
    s.listen()                   # the peer credentials are taken here: another user's
    print("listening", flush=True)
    conn, _ = s.accept()
    conn.recv(1)
    """
)


@root_only
def test_the_client_refuses_a_listener_running_as_another_user(tmp_path: Path):
    """The file check and the connect are two steps; SO_PEERCRED closes the gap between them."""
    path = tmp_path / "usmswitchd.sock"
    proc = subprocess.Popen(
        [sys.executable, "-c", SWAPPER.format(uid=NOBODY), str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "listening"
        assert os.stat(path).st_uid == 0
        with pytest.raises(UntrustedSocketError, match=f"runs as .*uid {NOBODY}"):
            Client(str(path), timeout=2)
    finally:
        proc.kill()
        proc.wait(timeout=10)
        proc.stdout.close()


def test_a_path_that_is_not_a_socket_is_refused(tmp_path: Path):
    f = tmp_path / "usmswitchd.sock"
    f.write_text("")
    with pytest.raises(UntrustedSocketError, match="not a socket"):
        Client(str(f), timeout=1)
    with pytest.raises(FileNotFoundError):
        Client(str(tmp_path / "missing.sock"), timeout=1)


def test_a_rig_instance_socket_is_looked_for_after_usmswitch_socket() -> None:
    from usmswitch.protocol.sockets import client_socket_paths, rig_socket_path

    assert rig_socket_path("rigA") == Path("/run/usmswitch/rigA/usmswitchd.sock")
    paths = client_socket_paths({"USMSWITCH_SOCKET": "/a.sock", "USMSWITCH_RIG": "rigB"})
    assert paths[:2] == [Path("/a.sock"), Path("/run/usmswitch/rigB/usmswitchd.sock")]
    for bad in ("", "../etc", "a/b", ".hidden"):
        with pytest.raises(ValueError, match="rig name"):
            rig_socket_path(bad)
