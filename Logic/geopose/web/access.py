"""Who may open the page: the server listens on the loopback address unless the user says
otherwise, and on any other address every request must present a token.

The page's address carries the token (``?token=...``); the first request that presents it
gets it back as a cookie, which the page's later requests (scripts, the websocket) send.
A request without either is answered 403 before it reaches the app.
"""

from __future__ import annotations

import ipaddress
import secrets

from ..errors import InputError

__all__ = ["LOOPBACK", "TOKEN_COOKIE", "is_loopback", "bind_token", "token_middleware", "page_url"]

#: The default address: this machine only.
LOOPBACK = "127.0.0.1"
#: Cookie (and query parameter ``token``) that carries the token.
TOKEN_COOKIE = "geopose_token"
#: Shortest token accepted from the user (characters).
MIN_TOKEN_CHARS = 16


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and the loopback addresses (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def bind_token(host: str, allow_remote: bool, token: str | None) -> str | None:
    """The token pages must present when listening on ``host`` (None: loopback without a token).

    Another address needs ``allow_remote`` (``--allow-remote``); its token is ``token`` when given
    (at least 16 characters), else a new random one. A token given on loopback is enforced too."""
    if not is_loopback(host) and not allow_remote:
        raise InputError(
            f"--host {host} would let other machines open the page: add --allow-remote (the page then needs "
            "the token printed with its address), or leave --host at 127.0.0.1"
        )
    if token is not None and len(token) < MIN_TOKEN_CHARS:
        raise InputError(f"--token has {len(token)} characters: give at least {MIN_TOKEN_CHARS} (or omit it for a random one)")
    if token is None and not is_loopback(host):
        token = secrets.token_urlsafe(24)
    return token


def token_middleware(token: str):
    """An aiohttp middleware that answers 403 unless the request presents ``token`` (query or cookie)."""
    from aiohttp import web

    @web.middleware
    async def check_token(request, handler):
        given = request.query.get("token") or request.cookies.get(TOKEN_COOKIE) or ""
        if not secrets.compare_digest(given.encode(), token.encode()):
            return web.Response(status=403, text="geopose view: this page needs the token printed with its address (?token=...)\n")
        response = await handler(request)
        if request.query.get("token") and not isinstance(response, web.WebSocketResponse):
            response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="Strict")
        return response

    return check_token


def page_url(host: str, port: int, token: str | None) -> str:
    """The address to open (``host`` as given; an IPv6 address in brackets)."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")
