"""Who may see the viewer: loopback addresses, and a token gate for a viewer served to the network.

viser serves its page and its WebSocket on one port with no authentication: anyone who reaches the port
sees every image of the template. `TokenGate` is a small TCP front on the public address that lets a
connection through to viser (listening on 127.0.0.1 only) when its first request carries the token:

- `GET /?token=T` is answered with a redirect to the same page without the token and a cookie holding it
  (HttpOnly, SameSite=Strict, named for the port): the browser sends it with every later request, the
  WebSocket's included (viser's client opens it on the page's URL without the query string);
- a request with that cookie is passed through, and the rest of its connection with it;
- any other request gets `403 Forbidden` and the connection is closed: no page, no WebSocket.

Tokens are compared in constant time. The traffic itself is plain HTTP.
"""
from __future__ import annotations

import asyncio
import hmac
import ipaddress
import re
import socket
import threading
from http.cookies import CookieError, SimpleCookie
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from gscan.errors import InputError

MAX_HEAD_BYTES = 16 * 1024  # a request head longer than this is refused
HEAD_TIMEOUT_S = 10.0  # a client that sends no complete request head in this time is dropped
_CHUNK = 1 << 16
_TOKEN_RE = re.compile(r"[A-Za-z0-9._~-]{1,256}")


def is_loopback(host: str) -> bool:
    """Whether `host` (an address or a name) binds to this machine only: every address it resolves to is a
    loopback address (127.0.0.0/8, ::1). The empty host and wildcard addresses (0.0.0.0, ::) are not."""
    if not host:
        return False
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(str(i[4][0]).split("%")[0]).is_loopback for i in infos)


def check_token(token: str) -> None:
    """InputError unless `token` can stand as it is in a URL and a cookie: 1-256 of A-Z a-z 0-9 . _ ~ -."""
    if not _TOKEN_RE.fullmatch(token):
        raise InputError(None, "the viewer's token must be 1-256 characters of A-Z a-z 0-9 . _ ~ -")


def cookie_name(port: int) -> str:
    """The token cookie of the viewer on `port` (cookies are kept per host, not per port)."""
    return f"gscan_token_{port}"


class TokenGate:
    """Serve `host:port`, passing connections that carry `token` on to 127.0.0.1:`upstream_port` (see the
    module docstring). `start()` binds (OSError when it cannot), `stop()` closes every connection."""

    def __init__(self, host: str, port: int, upstream_port: int, token: str):
        check_token(token)
        self.host, self.port, self.upstream_port = host, int(port), int(upstream_port)
        self._token = token.encode("utf-8")
        self._cookie = cookie_name(self.port)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="gscan-token-gate", daemon=True)
        self._server: asyncio.AbstractServer | None = None
        self._tasks: set[asyncio.Task] = set()

    # -- lifetime
    def start(self) -> None:
        self._thread.start()
        fut = asyncio.run_coroutine_threadsafe(self._start(), self._loop)
        try:
            fut.result(timeout=30)
        except BaseException:
            self.stop()
            raise

    async def _start(self) -> None:
        self._server = await asyncio.start_server(self._handle, self.host, self.port, reuse_address=True,
                                                  limit=MAX_HEAD_BYTES)

    def stop(self) -> None:
        if self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(self._stop(), self._loop).result(timeout=10)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)
        if not self._loop.is_running():
            self._loop.close()

    async def _stop(self) -> None:
        if self._server is not None:
            self._server.close()
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)

    # -- requests
    def _valid(self, token: str | None) -> bool:
        return token is not None and hmac.compare_digest(token.encode("utf-8", "surrogateescape"), self._token)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        try:
            await self._serve(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError,
                asyncio.CancelledError):
            pass
        finally:
            writer.close()
            if task is not None:
                self._tasks.discard(task)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = await asyncio.wait_for(_read_head(reader), HEAD_TIMEOUT_S)
        if head is None:
            await _respond(writer, 400, "Bad Request", "bad request\n")
            return
        target, cookies = _parse_head(head)
        url = urlsplit(target)
        query = parse_qsl(url.query, keep_blank_values=True)
        given = [v for k, v in query if k == "token"]
        if given:
            if not self._valid(given[-1]):
                await _respond(writer, 403, "Forbidden", "wrong token\n")
                return
            rest = urlencode([(k, v) for k, v in query if k != "token"])
            location = urlunsplit(("", "", url.path or "/", rest, ""))
            await _respond(writer, 303, "See Other", "", [
                ("Location", location),
                ("Set-Cookie", f"{self._cookie}={self._token.decode()}; Path=/; HttpOnly; SameSite=Strict"),
                ("Cache-Control", "no-store")])
            return
        if not self._valid(cookies.get(self._cookie)):
            await _respond(writer, 403, "Forbidden", "this gscan viewer needs its token: open the URL that "
                           "`gscan view` printed (it ends in ?token=...)\n")
            return
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port)
        try:
            up_writer.write(head)
            await up_writer.drain()
            pipes = [asyncio.ensure_future(_pipe(reader, up_writer)), asyncio.ensure_future(_pipe(up_reader, writer))]
            try:
                await asyncio.wait(pipes, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for p in pipes:
                    p.cancel()
                await asyncio.gather(*pipes, return_exceptions=True)
        finally:
            up_writer.close()


async def _read_head(reader: asyncio.StreamReader) -> bytes | None:
    """The request head up to and with its blank line; None when it is too long or the client left."""
    try:
        return await reader.readuntil(b"\r\n\r\n")  # the reader's limit is MAX_HEAD_BYTES
    except (asyncio.LimitOverrunError, asyncio.IncompleteReadError):
        return None


def _parse_head(head: bytes) -> tuple[str, dict[str, str]]:
    """(request target, {cookie name: value}) of a request head."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    target = parts[1] if len(parts) >= 2 else "/"
    cookies: dict[str, str] = {}
    for line in lines[1:]:
        name, _, value = line.partition(":")
        if name.strip().lower() == "cookie":
            try:
                jar = SimpleCookie()
                jar.load(value.strip())
            except CookieError:
                continue
            cookies.update({k: m.value for k, m in jar.items()})
    return target, cookies


async def _respond(writer: asyncio.StreamWriter, status: int, reason: str, body: str,
                   headers: list[tuple[str, str]] | None = None) -> None:
    data = body.encode("utf-8")
    lines = [f"HTTP/1.1 {status} {reason}", "Content-Type: text/plain; charset=utf-8",
             f"Content-Length: {len(data)}", "Connection: close", *(f"{k}: {v}" for k, v in headers or [])]
    writer.write(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + data)
    await writer.drain()


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while data := await reader.read(_CHUNK):
            writer.write(data)
            await writer.drain()
    except (ConnectionError, asyncio.CancelledError):
        pass
    finally:
        writer.close()
