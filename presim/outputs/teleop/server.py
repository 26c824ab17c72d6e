"""The teleop web server: starlette (ASGI) + uvicorn, one page and one WebSocket, bound to 127.0.0.1
by default. Every asset ships in ``static/`` inside the package (nothing from the internet). Every
request passes :func:`presim.outputs.teleop.access.refusal` first (Host, Origin, per-run token; 403).

WebSocket ``/ws``: the server sends text JSON (``init``, ``state``, ``info``, ``error``, ``reset``)
and binary messages ``kind (1 byte) | seq (uint32 big-endian) | payload`` with kind 1 = colour JPEG,
2 = depth JPEG (turbo, 0..depth_max_m), 3 = map PNG. Flow control drops frames instead of queueing
them: after a ``state`` the next one is sent only once the page acknowledged it (``{"type": "ack"}``)
or a second passed, and it is always the newest state -- a slow page sees fewer frames, never old ones.
"""

from __future__ import annotations

import asyncio
import itertools
import socket
import threading
import time
from collections import deque
from importlib import resources
from pathlib import Path

from presim.outputs.teleop.access import AccessPolicy, new_token, refusal
from presim.outputs.teleop.frames import encode_png
from presim.outputs.teleop.protocol import Ack, ProtocolError, parse_message
from presim.outputs.teleop.session import TeleopSession

__all__ = ["TeleopServer", "STATIC_DIR"]

STATIC_DIR = Path(str(resources.files("presim.outputs.teleop") / "static"))
KIND_COLOR, KIND_DEPTH, KIND_MAP = 1, 2, 3
ACK_TIMEOUT_S = 1.0
MAX_CLIENTS = 32
"""Tabs served at once; one more is told so and closed (code 1013). Each tab costs up to one frame
plus the socket's write buffer (about 0.1 MB at 640x480), so the bound keeps the server's memory
bounded whatever connects."""
OUTBOX_MAX = 64
"""Text messages queued for one tab at most (older ones are dropped): a tab that floods the server
with bad input, or stops reading, costs a bounded amount of memory."""


def release_free_memory() -> None:
    """Hand freed heap pages back to the system (glibc ``malloc_trim``; a no-op elsewhere): the
    buffers of closed tabs are freed by Python, but glibc keeps the pages mapped until trimmed."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _binary(kind: int, seq: int, payload: bytes) -> bytes:
    return bytes([kind]) + int(seq & 0xFFFFFFFF).to_bytes(4, "big") + payload


class _Client:
    def __init__(self, client_id: int, ws):
        self.id, self.ws = client_id, ws
        self.wake = asyncio.Event()
        self.outbox: deque[dict] = deque(maxlen=OUTBOX_MAX)
        self.sent_seq = self.acked_seq = 0
        self.image_seq = 0
        self.sent_at = 0.0


class TeleopServer:
    """Serve ``session`` on ``host:port`` (0 = a free port). ``start()`` runs it in a thread (tests);
    ``serve()`` blocks until Ctrl-C / SIGTERM (CLI). ``url`` carries the per-run token; only requests
    that pass :mod:`~presim.outputs.teleop.access` (token, Host, Origin; ``allow_origins`` opens it)
    are served."""

    def __init__(self, session: TeleopSession, host: str = "127.0.0.1", port: int = 0,
                 allow_origins: tuple[str, ...] = (), token: str | None = None, max_clients: int = MAX_CLIENTS):
        self.session, self.host = session, host
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((host, port))
            self.sock.listen(128)  # listening before the URL is printed; uvicorn accepts from it
        except OSError as e:
            self.sock.close()
            raise OSError(f"--port {port}: cannot listen on {host}:{port} ({e.strerror or e})") from None
        self.port = self.sock.getsockname()[1]
        self.token = token or new_token()
        self.policy = AccessPolicy(self.port, self.token, host, tuple(allow_origins))
        url_host = "127.0.0.1" if host in ("0.0.0.0", "") else "[::1]" if host == "::" else \
            f"[{host}]" if ":" in host else host
        self.base_url = f"http://{url_host}:{self.port}/"
        """The server's root without the token (``url`` is what a user opens)."""
        self.url = f"{self.base_url}?token={self.token}"
        self.refused = 0
        """Requests answered 403 so far."""
        self.clients: dict[int, _Client] = {}
        self.max_clients = max_clients
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._map_png = encode_png(session.map.rgb)
        self._server = None
        self._thread: threading.Thread | None = None
        session.notify = self._notify_threadsafe
        session.on_frame = self._frame_threadsafe

    # ---- ASGI app --------------------------------------------------------------------------------
    def app(self):
        from starlette.applications import Starlette
        from starlette.responses import FileResponse, JSONResponse
        from starlette.routing import Mount, Route, WebSocketRoute
        from starlette.staticfiles import StaticFiles

        async def index(request):
            return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-store"})

        async def health(request):
            s = self.session
            return JSONResponse({"clients": len(self.clients), "step": s.latest.state["step"] if s.latest else 0,
                                 "error": repr(s.error) if s.error else None})

        app = Starlette(routes=[
            Route("/", index),
            Route("/health", health),
            WebSocketRoute("/ws", self._ws),
            Mount("/static", StaticFiles(directory=STATIC_DIR), name="static"),
        ])
        return self._guard(app)

    def _guard(self, app):
        """ASGI wrapper: a request that :func:`refusal` refuses gets 403 (a WebSocket upgrade too,
        before it is accepted) and never reaches ``app``."""
        from starlette.responses import PlainTextResponse

        async def guarded(scope, receive, send):
            if scope["type"] in ("http", "websocket"):
                headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
                why = refusal(self.policy, method=scope.get("method", "GET"), path=scope["path"],
                              query=scope.get("query_string", b"").decode("latin-1"), headers=headers,
                              websocket=scope["type"] == "websocket")
                if why is not None:
                    self.refused += 1
                    if scope["type"] == "websocket":
                        await send({"type": "websocket.close", "code": 1008})  # uvicorn answers HTTP 403
                    else:
                        await PlainTextResponse(f"403 Forbidden: {why}\n", status_code=403)(scope, receive, send)
                    return
            await app(scope, receive, send)

        return guarded

    async def _ws(self, ws) -> None:
        from starlette.websockets import WebSocketDisconnect

        await ws.accept()
        self._loop = asyncio.get_running_loop()
        if len(self.clients) >= self.max_clients:
            try:
                await ws.send_json({"type": "error", "message": f"{len(self.clients)} tabs are open, the most "
                                    "this server serves: close one and reload"})
                await ws.close(code=1013, reason="too many tabs")
            except (WebSocketDisconnect, RuntimeError, ConnectionError):
                pass
            return
        c = _Client(next(self._ids), ws)
        self.clients[c.id] = c
        self.session.add_client(c.id)
        sender = asyncio.create_task(self._sender(c))
        try:
            await ws.send_json(self.session.init_message(c.id))
            await ws.send_bytes(_binary(KIND_MAP, 0, self._map_png))
            c.wake.set()
            while True:
                msg = await ws.receive()
                if msg["type"] == "websocket.disconnect":
                    break
                raw = msg.get("text") if msg.get("text") is not None else msg.get("bytes")
                try:
                    m = parse_message(raw, self.session.spec)
                except ProtocolError as e:
                    c.outbox.append({"type": "error", "message": f"refused: {e}"})
                    c.wake.set()
                    continue
                if isinstance(m, Ack):
                    c.acked_seq = max(c.acked_seq, m.seq)
                    c.wake.set()
                else:
                    self.session.submit(c.id, m)
        except (WebSocketDisconnect, RuntimeError, ConnectionError):
            pass
        finally:
            sender.cancel()
            try:
                await sender
            except (asyncio.CancelledError, Exception):  # noqa: BLE001 - the tab is gone either way
                pass
            self.clients.pop(c.id, None)
            self.session.remove_client(c.id)
            c.outbox.clear()
            if not self.clients:
                release_free_memory()

    async def _sender(self, c: _Client) -> None:
        ws = c.ws
        while True:
            try:
                await asyncio.wait_for(c.wake.wait(), timeout=ACK_TIMEOUT_S / 2)
            except asyncio.TimeoutError:
                pass
            c.wake.clear()
            while c.outbox:
                await ws.send_json(c.outbox.popleft())
            f = self.session.latest
            if f is None or f.seq <= c.sent_seq:
                continue
            if c.acked_seq < c.sent_seq and time.monotonic() - c.sent_at < ACK_TIMEOUT_S:
                continue  # the page is still drawing: this frame will be replaced by a newer one
            with_images = f.image_seq > c.image_seq and f.color_jpeg is not None
            state = dict(f.state, has_images=with_images, you=c.id)
            await ws.send_json(state)
            if with_images:
                await ws.send_bytes(_binary(KIND_COLOR, f.seq, f.color_jpeg))
                await ws.send_bytes(_binary(KIND_DEPTH, f.seq, f.depth_jpeg))
                c.image_seq = f.image_seq
            c.sent_seq, c.sent_at = f.seq, time.monotonic()

    # ---- from the sim thread ---------------------------------------------------------------------
    def _notify_threadsafe(self, client_id: int | None, msg: dict) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return

        def push():
            targets = self.clients.values() if client_id is None else [self.clients[client_id]] \
                if client_id in self.clients else []
            for c in targets:
                c.outbox.append(msg)
                c.wake.set()

        try:
            loop.call_soon_threadsafe(push)
        except RuntimeError:  # loop closed while shutting down
            pass

    def _frame_threadsafe(self) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return

        def wake():
            for c in self.clients.values():
                c.wake.set()

        try:
            loop.call_soon_threadsafe(wake)
        except RuntimeError:
            pass

    # ---- running ---------------------------------------------------------------------------------
    def _make_server(self):
        import uvicorn

        config = uvicorn.Config(self.app(), log_level="warning", ws="websockets-sansio", lifespan="off",
                                ws_max_size=1 << 16)
        self._server = uvicorn.Server(config)
        return self._server

    def serve(self) -> None:
        """Block until Ctrl-C / SIGTERM (uvicorn handles both and shuts down cleanly)."""
        self.session.start()
        try:
            self._make_server().run(sockets=[self.sock])
        finally:
            self.session.stop()
            self.sock.close()

    def start(self) -> str:
        """Start the session and the server in a background thread; returns the URL."""
        self.session.start()
        server = self._make_server()
        self._thread = threading.Thread(target=server.run, kwargs={"sockets": [self.sock]},
                                        name="presim-teleop-http", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 20
        while not server.started and time.monotonic() < deadline:
            if not self._thread.is_alive():
                raise RuntimeError("teleop server failed to start")
            time.sleep(0.05)
        return self.url

    def stop(self) -> None:
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(20)
        self.session.stop()
        self.sock.close()
