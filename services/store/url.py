"""The store URL: where it comes from and how it is shown. A password never travels on a command line (any user's
`ps` reads it there) and is never written to a log, an error event or a record: it comes from OCCVO_STORE_URL in the
environment, from a URL file readable by its owner only, or from PostgreSQL's own PGPASSWORD / PGPASSFILE /
~/.pgpass (libpq reads those itself); worker processes get it through their environment."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from urllib.parse import unquote

from occvo_core.errors import ConfigError

STORE_URL_ENV = "OCCVO_STORE_URL"
PG_SCHEMES = ("postgresql://", "postgres://")
SECRET_WAYS = (
    f"put the URL in {STORE_URL_ENV} in the environment, in a file named by --store-url-file (readable by its "
    "owner only), or the password in PGPASSFILE / ~/.pgpass"
)
SECRET_KEYS = ("password", "sslpassword")  # libpq's keywords holding a secret
HIDDEN = "***"

# a URL (scheme://...) or a conninfo keyword; the password of a URL is its userinfo after the first ':' up to the
# last '@' before the path (libpq and urllib split there), or a password= query parameter (libpq decodes its keys)
_URL = r"[A-Za-z][A-Za-z0-9+.-]*://\S+"
_CONNINFO = r"(?<![^\s'\"])(?:ssl)?password\s*=\s*(?:'(?:[^'\\]|\\.)*'?|[^\s'\"]*)"
_TOKEN = re.compile(f"({_URL})|({_CONNINFO})", re.IGNORECASE)
_USERINFO = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*://[^/\s:@]*):[^/\s]*@")
_PARAM = re.compile(r"([?&])([^=&#\s]*)=([^&#\s\"']*)")


def redact(text: str) -> str:
    """`text` with every store password it holds replaced by ***: a URL's (postgresql://user:pw@host/db, percent-
    encoded or not), a query's (?password=pw), a libpq conninfo's (password=pw, password='p w'). The one function
    every log line, error event, error line and record goes through."""
    if not isinstance(text, str) or ("@" not in text and "=" not in text):  # no userinfo, no key=value
        return text
    return _TOKEN.sub(_hide, text)


def _hide(m: re.Match) -> str:
    if m.group(2):  # conninfo keyword=value
        return m.group(2).split("=", 1)[0].rstrip() + "=" + HIDDEN
    url = _USERINFO.sub(lambda u: f"{u.group(1)}:{HIDDEN}@", m.group(1), count=1)
    return _PARAM.sub(_hide_param, url)


def _hide_param(m: re.Match) -> str:
    key = m.group(2)
    return f"{m.group(1)}{key}={HIDDEN}" if unquote(key).lower() in SECRET_KEYS else m.group(0)


def has_password(url: str | None) -> bool:
    """Whether a store URL (or conninfo) carries a password in any form."""
    return url is not None and redact(url) != url


def refuse_password(url: str | None, flag: str) -> str | None:
    """The URL given on a command line, refused when it holds a password."""
    if has_password(url):
        raise ConfigError(
            f"{flag} {redact(url)}: a password on the command line is refused (ps shows it to every user): {SECRET_WAYS}"
        )
    return url


def read_url_file(path: str | Path, flag: str = "--store-url-file") -> str:
    """The store URL in a file (its first line that is neither blank nor a # comment); the file must be readable by
    its owner only, as libpq asks of ~/.pgpass."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise ConfigError(f"{flag} {path}: not a regular file")
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(f"{flag} {path}: readable by others (mode {stat.S_IMODE(mode):04o}): chmod 600 {path}")
    lines = [s.strip() for s in text.splitlines() if s.strip() and not s.strip().startswith("#")]
    if not lines:
        raise ConfigError(f"{flag} {path}: holds no store URL")
    return lines[0]


def resolve(url: str | None, url_file: str | None, flag: str = "--store", env=None) -> str | None:
    """The store: `url` from the command line (no password allowed there), else the URL file, else OCCVO_STORE_URL;
    None without any."""
    env = os.environ if env is None else env
    if url and url_file:
        raise ConfigError(f"give {flag} or --store-url-file, not both")
    if url:
        return refuse_password(url, flag)
    if url_file:
        return read_url_file(url_file)
    return env.get(STORE_URL_ENV) or None


def is_postgres_url(url_or_path: str | Path | None) -> bool:
    return isinstance(url_or_path, str) and url_or_path.startswith(PG_SCHEMES)


def sqlite_path(url_or_path: str | Path) -> str:
    """The file of a path or of a sqlite:/// URL (SQLAlchemy's form: sqlite:///relative, sqlite:////absolute)."""
    s = str(url_or_path)
    return s[len("sqlite:///") :] if s.startswith("sqlite:///") else s
