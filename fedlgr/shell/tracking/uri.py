"""Tracking URIs: which store a command was given, and what of a URI may be shown (its passwords as
``***``). Light on purpose: the config and the CLI read it before anything heavy loads."""

from __future__ import annotations

import os
import re
import urllib.parse
from pathlib import Path

from fedlgr.errors import FedlgrError

DEFAULT_URI = "sqlite:///mlflow.db"


def resolve_uri(uri: str | None) -> str:
    """``uri`` if given, else ``$MLFLOW_TRACKING_URI``, else the local sqlite store."""
    if uri is not None and not uri.strip():
        raise FedlgrError("tracking URI '': empty; give one, or leave it unset for the default")
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI


DATABASES = ("sqlite", "postgresql", "mysql", "mssql")


def in_memory_sqlite(uri: str) -> bool:
    """Whether ``uri`` names an in-memory sqlite database (``sqlite://``, ``:memory:``,
    ``file::memory:``, ``mode=memory``), which keeps nothing once its process ends."""
    if not uri.startswith("sqlite:"):
        return False
    # lazy: sqlalchemy (~1 s); this module is read before anything heavy loads
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        url = make_url(uri)
    except (ArgumentError, ValueError):
        return False  # not a URL sqlalchemy reads: for the store's own check to refuse
    database = url.database or ""
    return (
        database in ("", ":memory:")
        or database.startswith("file::memory:")
        or url.query.get("mode") == "memory"
        or "mode=memory" in database
    )


def sqlite_file(url: str) -> Path | None:
    """The file an sqlite URL names, None for another database or an in-memory one; raises
    sqlalchemy's ``ArgumentError`` for a URL it cannot read."""
    # lazy: sqlalchemy (~1 s); this module is read before anything heavy loads
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or in_memory_sqlite(url):
        return None
    return Path(parsed.database).expanduser()


def given_uri(uri: str | None, overrides: list[str]) -> str:
    """The tracking URI a command was given: ``--tracking-uri``, else its last
    ``tracking.uri=`` override, else ``$MLFLOW_TRACKING_URI`` or the default."""
    given = [o.split("=", 1)[1] for o in overrides if o.startswith("tracking.uri=")]
    return resolve_uri(uri or (given[-1] if given else None))


def server_database(uri: str) -> bool:
    """Whether ``uri`` names a database server's database (``postgresql+psycopg://``, ...) rather
    than a file or an HTTP server; also a misspelt one (``postgres://``)."""
    scheme = uri.partition("://")[0].split("+", 1)[0].lower() if "://" in uri else ""
    return scheme in (*DATABASES[1:], "postgres", "mariadb")


def mask_password(uri: str) -> str:
    """``uri`` with its secrets as ``***``: the password of its ``user:password@`` part, an HTTP
    URI's token userinfo, and every query parameter named ``...password``, ``...token``,
    ``...secret``, ``...api_key`` or ``...access_key``. Not SQLAlchemy's
    ``render_as_string(hide_password=True)``: it shows what follows a password's ``@`` as the
    host, masks no query parameter and fails on some URLs."""
    scheme, sep, rest = uri.partition("://")
    if not sep:
        return uri
    at = rest.rfind("@", 0, authority_end(rest))
    user, colon, _ = rest[: max(at, 0)].partition(":")
    if at > 0 and _token_userinfo(scheme, rest[:at]):
        rest = f"***{rest[at:]}"
    elif at >= 0 and colon and "/" not in user:
        rest = f"{user}:***{rest[at:]}"
    return f"{scheme}://" + _QUERY_PARAM.sub(_masked_param, rest)


def _token_userinfo(scheme: str, userinfo: str) -> bool:
    """Whether an HTTP URI's userinfo is a token (``https://TOKEN@host``, ``TOKEN:@``,
    ``TOKEN:x-oauth-basic@``), as servers that take a token for a user name read it; a
    database's ``user@`` is a user name."""
    user, _, password = userinfo.partition(":")
    return (
        scheme.lower() in ("http", "https")
        and "/" not in user
        and password in ("", "x-oauth-basic")
    )


# a query (or fragment) parameter: its separator, name and value
_QUERY_PARAM = re.compile(r"([?&#;])([^=&#;]*)=([^&#;]*)")
# access_token, client_secret, api_key; not libpq's sslkey or MySQL's ssl_key: file paths
SECRET_PARAMS = ("password", "token", "secret", "api_key", "apikey", "access_key")


def _secret_param(name: str) -> bool:
    return urllib.parse.unquote(name).strip().lower().endswith(SECRET_PARAMS)


def _masked_param(m: re.Match) -> str:
    return f"{m.group(1)}{m.group(2)}=***" if _secret_param(m.group(2)) else m.group(0)


def authority_end(rest: str) -> int:
    """Where the query or fragment of a URL (after its ``scheme://``) begins."""
    return min((i for i in (rest.find("?"), rest.find("#")) if i >= 0), default=len(rest))


def _secrets(uri: str) -> set[str]:
    """The passwords ``uri`` holds, as written and decoded, and each ``@``-separated part of one (a
    parser that splits the URL at its first ``@`` shows the rest as a host name)."""
    scheme, sep, rest = uri.partition("://")
    if not sep:
        return set()
    at = rest.rfind("@", 0, authority_end(rest))
    found = {rest[:at].partition(":")[2]} if at > 0 else set()
    if at > 0 and _token_userinfo(scheme, rest[:at]):
        found.add(rest[:at].partition(":")[0])
    found |= {m.group(3) for m in _QUERY_PARAM.finditer(rest) if _secret_param(m.group(2))}
    forms = found | {urllib.parse.unquote(f) for f in found}
    forms |= {part for f in forms for part in f.split("@")}
    return {f for f in forms if len(f) >= 3}


def masked_text(text: str, uri: str) -> str:
    """``text`` without the URI's passwords: the URI as :func:`mask_password` writes it, and each
    password of three characters or more elsewhere (see :func:`_secrets`)."""
    text = text.replace(uri, mask_password(uri))
    for form in sorted(_secrets(uri), key=len, reverse=True):
        text = text.replace(form, "***")
    return text


_ANY_URI = re.compile(r"[A-Za-z][\w+.-]*://[^\s'\"<>]+")
# a "...password = value" pair (libpq's keyword connection strings: host=db password=...)
KEYWORD_PASSWORD = re.compile(r"(?i)(pass(?:word|%77ord)\s*=\s*)(?!\*\*\*)[^\s&;#'\"]+")


def masked_uris(text: str) -> str:
    """``text`` (another program's message) with the password of every URI in it, and of
    every ``password=...`` pair, as ``***``."""
    text = _ANY_URI.sub(lambda m: mask_password(m.group()), text)
    return KEYWORD_PASSWORD.sub(r"\1***", text)


def masked_echo(echo, *uris: str | None):
    """``echo`` (e.g. ``print``) that writes the passwords of ``uris`` as ``***``."""
    given = [u for u in uris if u]

    def say(*args: object, **kwargs) -> None:
        text = " ".join(map(str, args))
        for uri in given:
            text = masked_text(text, uri)
        echo(text, **kwargs)

    return say
