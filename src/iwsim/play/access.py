"""Who may reach the play server: the listening socket, the session token and the pages
allowed to open a session.

Kept free of heavy imports (no torch, no FastAPI), so ``iwsim play`` binds its port and
reads its token within a fraction of a second and fails fast when it cannot.

The rules:

- Every session needs the run's token (``?token=`` on ``/ws``, exactly once). Unless given
  (``--token-file``, ``$IWSIM_PLAY_TOKEN`` or ``--token``), it is random per run. The page
  gets it embedded only when served to this machine under a loopback name, so the local
  user notices nothing; remote users open ``/?token=SECRET``.
- A browser always sends ``Origin`` on a WebSocket: it must be the page's own origin
  (``http(s)://`` + the ``Host`` the server answers to) or one added with
  ``--allow-origin``. Any other page the user visits cannot open a session, and a page on
  a name that resolves to this machine (DNS rebinding) is not served at all.
- The token is never logged and never sent to another origin.
"""

from __future__ import annotations

import errno
import ipaddress
import os
import secrets
import socket
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from iwsim.core.errors import InputError, IwsimError
from iwsim.core.resources import read_capped

LOOPBACK = ("127.0.0.1", "localhost", "::1")
WILDCARD = ("0.0.0.0", "::", "")
TOKEN_ENV = "IWSIM_PLAY_TOKEN"
MIN_TOKEN_CHARS = 8
TOKEN_FILE_MAX_BYTES = 64 << 10


class PlayError(IwsimError):
    """The play server cannot start or had to stop."""


def check_bind(host: str, token: str | None) -> None:
    """Refuse to serve beyond this machine without a token chosen by the user (a random
    one would be unknown to the remote users, and is never printed)."""
    if host not in LOOPBACK and not token:
        raise InputError(f"refusing to bind {host} without --token: anyone who can reach it could drive "
                         "the simulator and write to the store; give a token with --token-file FILE or "
                         f"${TOKEN_ENV} (clients add ?token=SECRET).")


def resolve_token(flag: str | None = None, file: str | os.PathLike | None = None,
                  env: Mapping[str, str] | None = None) -> tuple[str | None, str]:
    """The token the user chose and where it came from: ``file`` (first line) over
    ``$IWSIM_PLAY_TOKEN`` over ``flag`` (the flag is visible to other users in ``ps``);
    (None, "random") when none was chosen."""
    env = os.environ if env is None else env
    if file is not None:
        try:
            lines = read_capped(file, TOKEN_FILE_MAX_BYTES).decode().splitlines()
        except InputError as e:
            raise InputError(f"the token file {e}") from None
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(f"cannot read the token file {file}: {getattr(e, 'strerror', None) or e}.") from None
        token, source = (lines[0].strip() if lines else ""), f"--token-file {file}"
    elif TOKEN_ENV in env:  # set but empty is a mistake to report, not a wish for a random token
        token, source = env[TOKEN_ENV].strip(), f"${TOKEN_ENV}"
    elif flag is not None:
        token, source = flag.strip(), "--token"
    else:
        return None, "random"
    if len(token) < MIN_TOKEN_CHARS or not token.isprintable() or " " in token:
        raise InputError(f"the token from {source} must be at least {MIN_TOKEN_CHARS} printable characters "
                         "without spaces.")
    return token, source


def new_token() -> str:
    return secrets.token_urlsafe(24)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: any free port), or a PlayError
    saying why not (port in use, no such address, ...)."""
    if not 0 <= port < 65536:
        raise InputError(f"--port must be in 0..65535 (0: any free port), got {port}.")
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, _, _, _, addr = infos[0]
        return socket.create_server(addr, family=family, backlog=128)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise PlayError(f"cannot serve on {host}:{port}: the address is already in use (another iwsim play?); "
                            "choose another --port.") from None
        raise PlayError(f"cannot serve on {host}:{port}: {e.strerror or e}.") from None


@dataclass(frozen=True)
class Access:
    """What the server checks on every request (see the module docstring)."""

    token: str
    bound_host: str
    port: int
    extra_origins: frozenset[str] = frozenset()

    @classmethod
    def create(cls, token: str | None, host: str, port: int, origins: Iterable[str] = ()) -> Access:
        extra = frozenset(check_origin(o) for o in origins)
        return cls(token or new_token(), host, port, extra)

    def known_host(self, host_header: str | None) -> bool:
        """Whether ``Host: host_header`` names this server: a loopback name with our port,
        the address we bound, or anything when bound to all interfaces (then the token
        guards alone)."""
        if self.bound_host in WILDCARD:
            return bool(host_header)
        names = {*LOOPBACK, self.bound_host}
        return host_header in {_host_port(n, self.port) for n in names}

    def page_token(self, host_header: str | None, client_ip: str | None) -> str | None:
        """The token to embed in the page: only for a browser on this machine that asked
        for a loopback name (so never for another machine, nor a rebound foreign name)."""
        loopback_names = {_host_port(n, self.port) for n in LOOPBACK}
        if host_header in loopback_names and client_ip is not None and _is_loopback_ip(client_ip):
            return self.token
        return None

    def origin_allowed(self, origin: str | None, host_header: str | None) -> bool:
        """A WebSocket's ``Origin``: absent (not a browser: the token decides), the page's
        own origin on a known host, or one of ``--allow-origin``."""
        if origin is None:
            return True
        if origin in self.extra_origins:
            return True
        return self.known_host(host_header) and origin in (f"http://{host_header}", f"https://{host_header}")

    def token_ok(self, values: list[str]) -> bool:
        """``values``: every ``token`` query parameter; exactly one, equal to ours."""
        return len(values) == 1 and secrets.compare_digest(values[0].encode(), self.token.encode())


def check_origin(origin: str) -> str:
    """An ``--allow-origin`` value: ``scheme://host[:port]``, no path."""
    from urllib.parse import urlsplit

    parts = urlsplit(origin)
    if parts.scheme not in ("http", "https") or not parts.netloc or parts.path not in ("", "/") or parts.query:
        raise InputError(f"--allow-origin must look like http://host:port, got {origin!r}.")
    return f"{parts.scheme}://{parts.netloc}"


def _host_port(host: str, port: int) -> str:
    """``host:port`` as a browser writes it in ``Host`` (no port for 80, IPv6 in brackets)."""
    name = f"[{host}]" if ":" in host else host
    return name if port == 80 else f"{name}:{port}"


def _is_loopback_ip(ip: str) -> bool:
    try:
        return ipaddress.ip_address(ip).is_loopback
    except ValueError:
        return False
