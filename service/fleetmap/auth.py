"""API tokens and roles for the REST API.

Tokens come from a file (`--auth-tokens FILE`) or the environment variable `FLEETMAP_TOKENS`, one
token per line as `ROLE TOKEN` (ROLE is `read`, `write` or `admin`; `#` at the start of a line or
after a space starts a comment, so a token may hold `#`). A token is at least 16 printable ASCII
characters (what an HTTP header carries as is). Clients send `Authorization: Bearer TOKEN`. `admin`
may do everything `write` may, `write` everything `read` may.

What needs which role:
- writing (POST scans, PUT/DELETE maps, DELETE regions, PUT snapshots and nav2 imports): `write`;
- reading (every GET, and POST /maps/{id}/cells and /raycast, which only read): `read`, unless
  reading is left open (`require_read=False`, the default), then anyone;
- signing a browser in (`POST /session`): a token of any role, whether reading is open or not;
- always open: `/healthz` (liveness probes carry no token), the web viewer's files (`GET /`,
  `/static/...`, `/vendor/leaflet/...`: they hold no map data, and the page must load to ask for a
  token), signing out (`DELETE /session`) and CORS preflights.
A token file is read again on SIGHUP (`TokenFile.reload`); tokens from the environment are fixed.
Tokens are compared in constant time against every configured token, and never logged.

Browser sessions: neither a browser's `<img>` tiles nor its `EventSource` can send an
`Authorization` header, so `POST /session` trades a token for the cookie `SESSION_COOKIE`, whose
value is the token's hex SHA-256 digest (`session_value`): a stolen cookie does not reveal the token,
and the cookie is matched against the configured digests on every request, so revoking the token
(token file, SIGHUP) ends the session at once. The cookie stands for its token on read requests only
(`is_read_request`), never on writes, so a page that gets a browser to send a request with it
(CSRF) can change no map; a bearer token (`Authorization: Bearer`), when sent, wins over the cookie
(another scheme, such as a proxy's `Basic`, does not: the cookie still counts).

Long requests: a request is let in by the tokens in force when it arrives, but an event stream runs
for hours. `AuthMiddleware` leaves the `Grant` it let a request in with in the ASGI scope
(`GRANT_SCOPE_KEY`), and the event stream checks it on every poll (`Grant.still_valid`): a token
revoked, or demoted below the role the request needed, ends its streams, as it ends its sessions.
"""

from __future__ import annotations

import codecs
import hashlib
import hmac
import json
import os
import re
import stat
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

from fleetmap.route_path import route_path

#: A token's role; each may do everything the roles before it may.
Role = Literal["read", "write", "admin"]
ROLES: tuple[str, ...] = get_args(Role)
_RANK = {role: rank for rank, role in enumerate(ROLES)}
TOKENS_ENV = "FLEETMAP_TOKENS"
#: Read-only requests that use POST.
_READ_POSTS = re.compile(r"^/maps/[^/]+/(cells|raycast)$")
#: Paths open to anyone, always.
_OPEN_PATHS = {"/healthz"}
#: The web viewer's files (`fleetmap.api.static`), open to GET and HEAD: they hold no map data, and
#: the page must load before it can ask its user for a token.
_VIEWER_PAGE = "/"
_VIEWER_FILE_PREFIXES = ("/static/", "/vendor/leaflet/")
#: Where a browser signs in (POST) and out (DELETE): `fleetmap.api.routes_session`.
SESSION_PATH = "/session"
#: The session cookie's name; its value is `session_value(token)`.
SESSION_COOKIE = "fleetmap_session"
#: A session cookie's value: a SHA-256 digest in lower-case hex.
_SESSION_VALUE = re.compile(r"^[0-9a-f]{64}$")
#: The most session cookies of one request that are looked up (each costs a comparison with every
#: configured token). A browser sends one per path and domain it holds one for: a few, or, with
#: cookies another page of the site set, up to its limit of cookies per domain (Chrome: 180).
MAX_SESSION_VALUES = 200
#: The ASGI scope key under which `AuthMiddleware` leaves the `Grant` it let a request in with.
GRANT_SCOPE_KEY = "fleetmap.grant"
#: The 401's detail for a session cookie that stands for no configured token: an unknown token's.
UNKNOWN_SESSION = "unknown token (the session cookie's token is unknown or was revoked: sign in again)"
#: A comment: `#` at the start of a line or after whitespace (a `#` inside a token is part of it).
_COMMENT = re.compile(r"(^|\s)#.*$")
#: A token file's path that is no path but what such a file holds (`ROLE TOKEN`, the form of
#: $FLEETMAP_TOKENS too), which the error about a file it cannot read would otherwise quote.
_NAMES_TOKENS = re.compile(r"^\s*(" + "|".join(ROLES) + r")\s+\S")
#: What a token may hold: printable ASCII, no space. A header's bytes are read as Latin-1, so any
#: other character could never match what a client sends (the clients check theirs against it too).
TOKEN_CHARACTERS = re.compile(r"^[\x21-\x7e]+$")

Scope = dict
Receive = Callable[[], Awaitable[dict]]
Send = Callable[[dict], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


class TokenFileError(ValueError):
    """The token file cannot be used; the message says which line and why (never the token)."""


@dataclass(frozen=True)
class TokenSet:
    """Configured tokens, stored as SHA-256 digests so equal-length constant-time comparison is easy."""

    digests: tuple[tuple[bytes, str], ...]  # (sha256(token), role)

    @classmethod
    def parse(cls, text: str, source: str = "tokens") -> TokenSet:
        entries = []
        listed: dict[bytes, tuple[str, int]] = {}  # digest -> (role, line)
        for lineno, raw in enumerate(text.splitlines(), 1):
            line = _COMMENT.sub("", raw).strip()
            if not line:
                continue
            parts = line.split()
            if len(parts) != 2 or parts[0] not in _RANK:
                raise TokenFileError(
                    f"{source}:{lineno}: expected 'ROLE TOKEN' with ROLE one of {', '.join(ROLES)}"
                )
            role, token = parts
            if len(token) < 16:
                raise TokenFileError(f"{source}:{lineno}: tokens must be at least 16 characters")
            if not TOKEN_CHARACTERS.match(token):
                raise TokenFileError(
                    f"{source}:{lineno}: tokens may hold only printable ASCII characters (no client "
                    "could send any other in an Authorization header)"
                )
            digest = _digest(token)
            if digest in listed:
                # Say which lines, never the token. A token listed again with another role is most
                # likely a demotion whose old line was left behind: neither role is safe to guess.
                earlier_role, earlier_line = listed[digest]
                if earlier_role != role:
                    raise TokenFileError(
                        f"{source}:{lineno}: this token is already listed on line {earlier_line} "
                        f"with the role {earlier_role!r}; list each token once"
                    )
                continue
            listed[digest] = (role, lineno)
            entries.append((digest, role))
        if not entries:
            raise TokenFileError(f"{source}: no tokens")
        return cls(tuple(entries))

    @classmethod
    def load(cls, path: str | None, environ: dict[str, str] | None = None) -> TokenSet | None:
        """Tokens from `path`, else from $FLEETMAP_TOKENS, else None (no authentication). Raises
        TokenFileError for a file or variable that holds none (an empty $FLEETMAP_TOKENS too)."""
        env = os.environ if environ is None else environ
        if path:
            try:
                raw = Path(path).read_bytes()
            except OSError as exc:
                if _NAMES_TOKENS.match(path):  # the tokens themselves, where a path goes: never quoted
                    raise TokenFileError(
                        "the token file's path (--auth-tokens, $FLEETMAP_AUTH_TOKENS) holds 'ROLE TOKEN' "
                        f"lines instead (not shown): put them in a file, or in ${TOKENS_ENV}"
                    ) from None
                raise TokenFileError(f"cannot read token file {path}: {exc.strerror}") from None
            # Windows editors (Notepad) start UTF-8 files with a byte order mark: it was read as part
            # of the first role, and a file that looked right was refused ("expected 'ROLE TOKEN'").
            body = raw.removeprefix(codecs.BOM_UTF8)
            try:
                text = body.decode("utf-8")
            except UnicodeDecodeError as exc:  # the message names the offset, never the bytes
                start = exc.start + len(raw) - len(body)
                line = raw[:start].count(b"\n") + 1
                raise TokenFileError(f"{path}:{line}: not UTF-8 text (byte {start})") from None
            return cls.parse(text, path)
        if TOKENS_ENV in env:
            text = env[TOKENS_ENV]
            if not text.strip():
                # Set but empty, as a template leaves an unset variable (`FLEETMAP_TOKENS=${TOKENS}`):
                # tokens were meant, and taking it for none served everyone without one, silently.
                raise TokenFileError(
                    f"${TOKENS_ENV} is set but holds no tokens: give it 'ROLE TOKEN; ROLE TOKEN', or "
                    "unset it to serve without tokens"
                )
            return cls.parse(text.replace(";", "\n"), f"${TOKENS_ENV}")
        return None

    def role_of(self, token: str) -> str | None:
        """The role of `token`, comparing against every configured token in constant time."""
        return self.role_of_digest(_digest(token))

    def role_of_session(self, value: str) -> str | None:
        """The role of the token whose session cookie holds `value` (`session_value(token)`), compared
        as `role_of` compares tokens; None for a value that is no configured token's (unknown,
        revoked, or not a digest at all)."""
        if not _SESSION_VALUE.match(value):
            return None
        return self.role_of_digest(bytes.fromhex(value))

    def role_of_digest(self, digest: bytes) -> str | None:
        """The highest role listed for `digest`, compared against every configured digest in
        constant time (no early exit: how long it takes says nothing of which one matched)."""
        found = None
        for known, role in self.digests:
            if hmac.compare_digest(known, digest) and (found is None or _RANK[role] > _RANK[found]):
                found = role
        return found


def others_may_read(path: str) -> str | None:
    """A warning if users other than the file's owner may read the token file `path` (its mode
    grants read to its group or to others), else None (also when it cannot be looked at: reading it
    then fails with its own message). Anyone who can read the file holds its tokens, an admin's
    among them, and a file written with the usual umask 022 is readable by every user of the
    machine. A warning, not a refusal: Kubernetes and Docker mount secrets readable by all (0644,
    0444) inside a container where no other user runs."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if not mode & (stat.S_IRGRP | stat.S_IROTH):
        return None
    who = "every user of this machine" if mode & stat.S_IROTH else "the users of its group"
    return (
        f"the token file {path} is readable by {who} (mode {stat.S_IMODE(mode):04o}): they can use "
        f"its tokens; make it readable by the service's user only (chmod 600 {path})"
    )


def session_value(token: str) -> str:
    """The session cookie's value for `token`: its SHA-256 digest in hex, the form `TokenSet` keeps
    it in, so the cookie never holds the token itself."""
    return _digest(token).hex()


def session_cookie(value: str, *, secure: bool, path: str) -> str:
    """The `Set-Cookie` value that signs a browser in with `value` (`session_value`). `HttpOnly`: the
    page's scripts cannot read it; `SameSite=Strict`: another site's page never makes the browser
    send it; `Path=<path>`, the path the service is served under (`/`, or `--root-path`'s): every
    request of the viewer carries it, and none to another application of the host (another
    fleetmap under another prefix, which would overwrite it with its own); `Secure` when the request
    came over https; no `Max-Age`: it ends when the browser closes (or at once when its token is
    revoked)."""
    return _with_cookie_attributes(f"{SESSION_COOKIE}={value}", secure, path)


def cleared_session_cookie(*, secure: bool, path: str) -> str:
    """The `Set-Cookie` value that signs a browser out: the session cookie, empty and expired (with
    the same attributes, or the browser would keep the cookie it has)."""
    return _with_cookie_attributes(f"{SESSION_COOKIE}=; Max-Age=0", secure, path)


def _with_cookie_attributes(cookie: str, secure: bool, path: str) -> str:
    return f"{cookie}; HttpOnly; SameSite=Strict; Path={path}" + ("; Secure" if secure else "")


def is_read_request(method: str, path: str) -> bool:
    """Whether a request only reads: every GET and HEAD, and POST /maps/{id}/cells and /raycast."""
    return method in ("GET", "HEAD") or (method == "POST" and _READ_POSTS.match(path) is not None)


def is_viewer_file(path: str) -> bool:
    """Whether `path` is one of the web viewer's files: its page `/`, or under `/static/` or
    `/vendor/leaflet/` (open to GET and HEAD; `fleetmap.api.security_headers` gives them their
    policy)."""
    return path == _VIEWER_PAGE or path.startswith(_VIEWER_FILE_PREFIXES)


def required_role(method: str, path: str, require_read: bool) -> str | None:
    """The role a request needs, or None if it is open."""
    if path in _OPEN_PATHS or method == "OPTIONS":  # CORS preflights carry no credentials
        return None
    if method in ("GET", "HEAD") and is_viewer_file(path):
        return None
    if path == SESSION_PATH:
        # Signing in takes a valid token of any role even where reads are open (it is what the
        # route checks); signing out only clears the browser's cookie, and must work once the
        # token is revoked too.
        return "read" if method == "POST" else None
    if is_read_request(method, path):
        return "read" if require_read else None
    return "write"


class TokenFile:
    """The tokens of a token file, read again by `reload` (`fleetmap serve` calls it on SIGHUP), so
    tokens can be added or revoked without a restart. A file that cannot be used keeps the tokens in
    force and raises `TokenFileError`: a typo must not lock every client out, or let anyone in."""

    def __init__(self, path: str) -> None:
        self.path = path
        loaded = TokenSet.load(path)
        assert loaded is not None  # a path is given
        self.current = loaded

    def reload(self) -> int:
        """Read the file again and use its tokens from now on; returns how many. Raises
        TokenFileError (the old tokens stay) if the file cannot be read or holds no valid tokens."""
        loaded = TokenSet.load(self.path)
        assert loaded is not None
        self.current = loaded  # one reference assignment: requests see the old set or the new one
        return len(loaded.digests)

    def role_of(self, token: str) -> str | None:
        return self.current.role_of(token)

    def role_of_session(self, value: str) -> str | None:
        return self.current.role_of_session(value)

    def role_of_digest(self, digest: bytes) -> str | None:
        return self.current.role_of_digest(digest)


class Grant:
    """What let a request in: a configured token (its digest: the bearer token's, or the one a
    session cookie holds) and the role the request needed. `AuthMiddleware` leaves it in the scope
    (`GRANT_SCOPE_KEY`) for requests that outlive the moment they were let in (event streams)."""

    def __init__(self, tokens: TokenSet | TokenFile, digest: bytes, needed: str) -> None:
        self.tokens = tokens
        self.digest = digest
        self.needed = needed
        #: The token set last checked against, and what it said: a stream asks ten times a second,
        #: and the tokens change only on SIGHUP, so the comparisons run once per reload.
        self._checked: TokenSet | None = None
        self._valid = True

    def still_valid(self) -> bool:
        """Whether the tokens in force now (the token file as last read, on SIGHUP) would let the
        request in: its token is still configured, with at least the role it needed."""
        current = self.tokens.current if isinstance(self.tokens, TokenFile) else self.tokens
        if current is not self._checked:
            role = current.role_of_digest(self.digest)
            self._valid = role is not None and _RANK[role] >= _RANK[self.needed]
            self._checked = current
        return self._valid


class AuthMiddleware:
    """ASGI middleware answering 401 (no or unknown token) or 403 (role too low) with a JSON detail.

    The token is the `Authorization: Bearer` header's; without one, a read request
    (`is_read_request`) may carry a session cookie instead (see the module's docstring; of several,
    the first that stands for a configured token counts: `_sessions`). An unknown or revoked session
    is the same 401 as an unknown token. A request let in carries its `Grant` in its scope
    (`GRANT_SCOPE_KEY`)."""

    def __init__(self, app: ASGIApp, tokens: TokenSet | TokenFile, require_read: bool = False) -> None:
        self.app = app
        self.tokens = tokens
        self.require_read = require_read

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        needed = required_role(scope["method"], route_path(scope), self.require_read)
        if needed is None:
            await self.app(scope, receive, send)
            return
        reads = is_read_request(scope["method"], route_path(scope))
        credential = _credential(scope.get("headers", []), self.tokens, reads)
        if credential is None:
            await _deny(send, 401, f"this request needs a token with the {needed!r} role: "
                        "send 'Authorization: Bearer <token>'")  # fmt: skip
            return
        role, digest, bearer = credential
        if role is None or digest is None:
            await _deny(send, 401, "unknown token" if bearer else UNKNOWN_SESSION)
            return
        if _RANK[role] < _RANK[needed]:
            await _deny(send, 403, f"this request needs the {needed!r} role; the token has {role!r}")
            return
        scope[GRANT_SCOPE_KEY] = Grant(self.tokens, digest, needed)
        await self.app(scope, receive, send)


def _credential(
    headers: Iterable[tuple[bytes, bytes]], tokens: TokenSet | TokenFile, reads: bool
) -> tuple[str | None, bytes | None, bool] | None:
    """What a request's credential stands for: (its role, None if it stands for no configured token;
    the token's digest; whether it was a bearer token), or None if it carries none. The token is the
    `Authorization: Bearer` header's; without one, a read (`reads`) may carry a session cookie."""
    headers = list(headers)
    token = bearer_token(headers)
    if token is not None:
        digest = _digest(token)
        return tokens.role_of_digest(digest), digest, True
    # The cookie counts only where no header is sent, and only for reads (never a write: CSRF).
    sessions = _sessions(headers) if reads else []
    if not sessions:
        return None
    # The first that stands for a configured token: a browser sends every session cookie it holds
    # for the request's host and path, another page's first (a longer Path, or set earlier; RFC
    # 6265, 5.4), and one it cannot read must not hide the viewer's own.
    for value in sessions:
        role = tokens.role_of_session(value)
        if role is not None:
            return role, bytes.fromhex(value), False
    return None, None, False


def may_read(
    headers: Iterable[tuple[bytes, bytes]], tokens: TokenSet | TokenFile | None, require_read: bool
) -> bool:
    """Whether a request with `headers` may read the maps, as `AuthMiddleware` would let a read in:
    always without tokens or without `require_read`, else with a credential (`_credential`) that
    stands for a configured token, of any role. For the open routes (`/healthz`) that answer more
    to a reader than to anyone."""
    if tokens is None or not require_read:
        return True
    credential = _credential(headers, tokens, reads=True)
    return credential is not None and credential[0] is not None


def bearer_token(headers: Iterable[tuple[bytes, bytes]]) -> str | None:
    """The token of an ASGI request's `Authorization: Bearer <token>` header, or None."""
    for name, value in headers:
        if name.lower() == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            if scheme.lower() == "bearer" and token.strip():
                return token.strip()
    return None


def _sessions(headers: Iterable[tuple[bytes, bytes]]) -> list[str]:
    """The values of an ASGI request's session cookies (`SESSION_COOKIE`), in the order sent, each
    once, at most `MAX_SESSION_VALUES`; empty without one.

    All of them, not only the first: a browser holds one cookie per name, domain and path, and sends
    every one that applies, longest path first. A `fleetmap_session` another page of the site set
    (another service on the same host, any port; a sibling subdomain, for the parent domain; with
    `Path=/maps`) came before the viewer's own, and taking only the first locked the viewer out for
    good: every read 401, and signing in again set the cookie that stays behind the other."""
    found: dict[str, None] = {}  # an ordered set
    for name, value in headers:
        if name.lower() != b"cookie":  # `name=value; name=value` (RFC 6265, 4.2.1)
            continue
        for pair in value.decode("latin-1").split(";"):
            key, equals, session = pair.partition("=")
            if equals and key.strip() == SESSION_COOKIE and session.strip():
                found[session.strip()] = None
                if len(found) == MAX_SESSION_VALUES:
                    return list(found)
    return list(found)


#: The challenge of every 401 (RFC 9110, 11.6.1): the scheme the API takes.
CHALLENGE = 'Bearer realm="fleetmap"'


def revoked_during(scope: Mapping[str, Any]) -> str | None:
    """Why a request let in by a token may not finish what it came for, or None: its token was
    revoked, or demoted below the role it needed, since it was let in (`Grant.still_valid`). For a
    write that takes minutes to arrive (a snapshot upload), checked before it changes anything: a
    token revoked meanwhile replaced the map all the same. None for a request let in without one."""
    grant = scope.get(GRANT_SCOPE_KEY)
    if grant is None or grant.still_valid():
        return None
    return (
        f"the token this request was sent with was revoked, or lost the {grant.needed!r} role, while "
        "its body was read: nothing changed"
    )


async def _deny(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if status == 401:
        headers.append((b"www-authenticate", CHALLENGE.encode()))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode()).digest()
