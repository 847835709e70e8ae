"""A loopback TCP relay that holds each new connection's bytes for a while before passing them on: a Zenoh
link whose handshake completes only after ``delay_s`` (a slow or congested network, a busy peer). Real sockets,
real Zenoh on both sides; only the timing of the link is controlled."""

from __future__ import annotations

import contextlib
import socket
import threading

from eqa.launcher import free_port


class SlowLink:
    """``SlowLink(target_port, delay_s)``: listen on a free loopback port (:attr:`port`); each accepted
    connection is relayed to ``127.0.0.1:target_port``, the client's bytes only after ``delay_s``. Context
    manager; closing stops accepting and cuts the relayed connections."""

    def __init__(self, target_port: int, delay_s: float) -> None:
        self.target_port = target_port
        self.delay_s = delay_s
        self.port = free_port()
        self._srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._srv.bind(("127.0.0.1", self.port))
        self._srv.listen(16)
        self._socks: list[socket.socket] = []
        self._closed = threading.Event()
        threading.Thread(target=self._accept, name="slow-link", daemon=True).start()

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._srv.accept()
                upstream = socket.create_connection(("127.0.0.1", self.target_port), timeout=5)
            except OSError:
                return
            upstream.settimeout(None)
            self._socks += [client, upstream]
            threading.Thread(target=self._pipe, args=(client, upstream, self.delay_s), daemon=True).start()
            threading.Thread(target=self._pipe, args=(upstream, client, 0.0), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, delay_s: float) -> None:
        if delay_s > 0 and self._closed.wait(delay_s):
            return
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                dst.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self._closed.set()
        self._srv.close()
        for s in self._socks:
            with contextlib.suppress(OSError):
                s.close()

    def __enter__(self) -> SlowLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

