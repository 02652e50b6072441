"""Callbacks for notifications, on a thread of their own (python-can's Notifier is the model).

    from usmswitch.client import Notifier

    def show(note):
        print(note.payload["cycle"], note.payload["error_ns"])

    with Notifier(listeners=[show], topics=["stroke"]):
        input("strokes are printed as they come; Enter ends\\n")

The Notifier opens its own connection (a `Client` is not shared between threads), subscribes and
hands every notification to each listener in order: a plain callable, or a `Listener` whose
`on_error` hears of a broken connection or of its own exception.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Iterable
from typing import Any

from .connection import DEFAULT_TIMEOUT, Client, ConnectionClosed
from .types import Notification

log = logging.getLogger("usmswitch.client.notifier")

# How often the thread looks up from an idle socket to see whether it was told to stop.
_POLL_S = 0.2


class Listener:
    """Receives notifications from a `Notifier`; override `on_notification` (and the others as needed)."""

    def on_notification(self, note: Notification) -> None:
        """One notification, on the Notifier's thread."""

    def on_error(self, exc: Exception) -> None:
        """This listener raised `exc`, or the connection broke (the Notifier then stops)."""
        log.error("usmswitch notifier: %s: %s", type(exc).__name__, exc)

    def stop(self) -> None:
        """The Notifier stopped: nothing more will come."""

    def __call__(self, note: Notification) -> None:
        self.on_notification(note)


ListenerLike = Listener | Callable[[Notification], Any]


class Notifier:
    """Calls listeners for every notification of `topics`, from a background thread.

    `source`: a socket address, a `Client` (its address and token are used for a connection of
    the Notifier's own), or None to find the local daemon as `Client()` does.
    """

    def __init__(
        self,
        source: Client | str | os.PathLike[str] | None = None,
        listeners: Iterable[ListenerLike] = (),
        topics: Iterable[str] = ("stroke",),
        *,
        rig: str | None = None,
        timeout: float | None = DEFAULT_TIMEOUT,
        token: str | None = None,
    ) -> None:
        if isinstance(source, Client):
            address: Any = source.address if source.family == "unix" else _tcp_url(source)
            token = token or source.token
        else:
            address = source
        self.listeners: list[ListenerLike] = list(listeners)
        self.topics = list(topics)
        #: Why the thread ended, when it was not told to (the connection broke).
        self.exception: Exception | None = None
        self._client = Client(address, timeout=timeout, token=token, rig=rig)
        self._client.subscribe(*self.topics)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="usmswitch-notifier", daemon=True)
        self._thread.start()

    def add_listener(self, listener: ListenerLike) -> None:
        self.listeners.append(listener)

    def remove_listener(self, listener: ListenerLike) -> None:
        self.listeners.remove(listener)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread, close the connection, tell the listeners."""
        self._stopping.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        self._client.close()
        for listener in list(self.listeners):
            if isinstance(listener, Listener):
                listener.stop()

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                note = self._client.next_notification(_POLL_S)
            except TimeoutError:
                continue
            except (ConnectionClosed, OSError) as exc:
                if not self._stopping.is_set():
                    self.exception = exc
                    self._tell_error(None, exc)
                return
            if note.topic not in self.topics:
                continue  # the server's own ("dropped", "error") are not asked for
            for listener in list(self.listeners):
                try:
                    listener(note)
                except Exception as exc:  # one listener's bug must not silence the others
                    self._tell_error(listener, exc)

    def _tell_error(self, culprit: ListenerLike | None, exc: Exception) -> None:
        targets = self.listeners if culprit is None else [culprit]
        told = False
        for listener in targets:
            if isinstance(listener, Listener):
                listener.on_error(exc)
                told = True
        if not told:
            log.error("usmswitch notifier: %s: %s", type(exc).__name__, exc)


def _tcp_url(client: Client) -> str:
    host, port = client.address
    return f"tcp://{host}:{port}"
