"""The store URL's password: redacted in every form wherever the URL is shown (logs, error events, error lines), refused
on a command line, read from OCCVO_STORE_URL or a URL file readable by its owner only; an unreachable PostgreSQL
store named (without the password) with the reason, before any worker starts. A real PostgreSQL server where one runs
(a role that needs its password over TCP), real files, real worker processes."""

from __future__ import annotations

import io
import json
import logging
import os
import subprocess
import sys
import time

import pytest

from occvo_core.errors import ConfigError
from occvo_services.sessions import free_port
from occvo_services.store.errors import StoreUnavailable
from occvo_services.store.factory import check_reachable, open_store
from occvo_services.store.url import SECRET_WAYS, STORE_URL_ENV, has_password, read_url_file, redact, resolve

PASSWORD = "s3cr@t-Pw"  # the role's
SECRET = "s3cr%40t-Pw"  # as a URL holds it, percent-encoded
FORMS = [
    ("postgresql://occvo:{pw}@db.lan:5432/occvo", "{pw}"),
    ("postgres://occvo:{pw}@[::1]:5432/occvo?sslmode=require", "{pw}"),
    ("postgresql://occvo:p@ss{pw}@db.lan/occvo", "p@ss{pw}"),  # an unencoded @ in the password
    ("postgresql://occvo@db.lan/occvo?password={pw}&sslmode=require", "{pw}"),
    ("postgresql://occvo@db.lan/occvo?sslmode=require&pass%77ord={pw}", "{pw}"),  # libpq decodes the key
    ("postgresql://occvo@db.lan/occvo?sslpassword={pw}", "{pw}"),
    ("host=db.lan user=occvo password={pw} dbname=occvo", "{pw}"),
    ("host=db.lan password = '{pw} with \\' quote' dbname=occvo", "{pw} with \\' quote"),
    ('connection to "postgresql://occvo:{pw}@db.lan/occvo" failed', "{pw}"),
]


@pytest.mark.parametrize("form, secret", FORMS, ids=[f for f, _ in FORMS])
def test_every_form_of_a_store_password_is_redacted(form, secret):
    text, secret = form.format(pw=SECRET), secret.format(pw=SECRET)
    shown = redact(text)
    assert secret not in shown and "s3cr" not in shown and "***" in shown, shown
    assert "db.lan" in shown or "[::1]" in shown  # the store is still named
    assert "occvo" in shown and has_password(text)
    assert redact(shown) == shown  # redacting twice changes nothing


@pytest.mark.parametrize(
    "text",
    [
        "postgresql://occvo@db.lan:5432/occvo?sslmode=verify-full",
        "var/occvo.sqlite",
        "sqlite:////var/lib/a:b@c/occvo.sqlite",
        "/tmp/password=1/x.sqlite",
        'FATAL:  password authentication failed for user "occvo"',
        "seq 4 not stored, pose not published",
    ],
)
def test_text_without_a_password_is_left_as_it_is(text):
    assert redact(text) == text and not has_password(text)


def test_a_log_line_never_holds_the_password():
    """Every field and the message of a JSON log line pass through redact (telemetry's formatter)."""
    from occvo_services.telemetry import _JsonFormatter, log_event

    out = io.StringIO()
    log = logging.getLogger("occvo.test-secrets")
    handler = logging.StreamHandler(out)
    handler.setFormatter(_JsonFormatter())
    log.addHandler(handler)
    log.propagate = False
    try:
        url = f"postgresql://occvo@db.lan/occvo?password={SECRET}"
        log_event(log, f"opening {url}", logging.WARNING, store=url, error=RuntimeError(f"bad {url}"))
    finally:
        log.removeHandler(handler)
    line = json.loads(out.getvalue())
    assert SECRET not in out.getvalue() and line["store"] == "postgresql://occvo@db.lan/occvo?password=***"
    assert "***" in line["event"] and "***" in line["error"]


def test_an_error_event_never_holds_the_password():
    """A worker's error event (e.g. `not_stored` naming the store) is redacted before it is logged or published."""
    from occvo_services.map_service import MapService
    from occvo_services.worker_config import WorkerConfig

    worker = MapService(WorkerConfig(worker_id="map-secrets", log_level="CRITICAL"))
    event = worker.report_error(
        "car0", "not_stored", f"trajectory store postgresql://occvo:{SECRET}@db.lan/occvo unreachable", seq=3
    )
    assert SECRET not in event.message and "postgresql://occvo:***@db.lan/occvo" in event.message


def test_a_url_file_must_be_its_owners_alone(tmp_path):
    path = tmp_path / "store.url"
    path.write_text(f"# the store\n\npostgresql://occvo:{SECRET}@db.lan/occvo\n")
    path.chmod(0o644)
    with pytest.raises(ConfigError, match=r"readable by others \(mode 0644\): chmod 600"):
        read_url_file(path)
    path.chmod(0o600)
    assert read_url_file(path) == f"postgresql://occvo:{SECRET}@db.lan/occvo"
    with pytest.raises(ConfigError, match="No such file"):
        read_url_file(tmp_path / "none.url")
    (tmp_path / "empty.url").write_text("# nothing\n")
    (tmp_path / "empty.url").chmod(0o600)
    with pytest.raises(ConfigError, match="holds no store URL"):
        read_url_file(tmp_path / "empty.url")


def test_the_store_comes_from_the_flag_the_file_or_the_environment(tmp_path):
    path = tmp_path / "store.url"
    path.write_text("postgresql://from-file@db.lan/occvo\n")
    path.chmod(0o600)
    env = {STORE_URL_ENV: "postgresql://from-env@db.lan/occvo"}
    assert resolve("postgresql://from-flag@db.lan/occvo", None, env=env) == "postgresql://from-flag@db.lan/occvo"
    assert resolve(None, str(path), env=env) == "postgresql://from-file@db.lan/occvo"
    assert resolve(None, None, env=env) == "postgresql://from-env@db.lan/occvo"
    assert resolve(None, None, env={}) is None
    with pytest.raises(ConfigError, match="not both"):
        resolve("x.sqlite", str(path), env={})
    with pytest.raises(ConfigError) as refused:
        resolve(f"postgresql://occvo:{SECRET}@db.lan/occvo", None, env={})
    assert SECRET not in str(refused.value) and SECRET_WAYS in str(refused.value)


def test_a_worker_refuses_a_password_on_its_command_line():
    """One line naming the ways a password may come, exit 2, before it connects to anything."""
    url = f"postgresql://occvo:{SECRET}@127.0.0.1:{free_port()}/occvo"
    for flag in ("--store-url", "--store-path"):
        out = subprocess.run(
            [sys.executable, "-m", "occvo_services.map_service", flag, url, "--connect", "tcp/127.0.0.1:1"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1 and SECRET not in out.stderr, out.stderr
        assert f"{flag} postgresql://occvo:***@" in lines[0] and STORE_URL_ENV in lines[0]


@pytest.mark.parametrize("way", ["environment", "url file"])
def test_a_worker_takes_its_store_without_argv_and_names_it_without_the_password(pg_cluster, tmp_path, way):
    """The map service given the store in OCCVO_STORE_URL (the way `occvo serve` hands it over) or in
    --store-url-file opens it with the password (the role needs it) and logs it without; with the database away its
    traceback holds no password."""
    from occvo_services.sessions import open_router

    user = f"occvo_{way.split()[0]}"
    pg_cluster.add_password_user(user, PASSWORD)
    url = f"postgresql://{user}:{SECRET}@127.0.0.1:{pg_cluster.port}/postgres"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    url_file = tmp_path / "store.url"
    url_file.write_text(url + "\n")
    url_file.chmod(0o600)
    cmd = [sys.executable, "-m", "occvo_services.map_service", "--connect", endpoint]
    cmd += ["--store-url-file", str(url_file)] if way == "url file" else []
    env = {**os.environ, STORE_URL_ENV: url} if way == "environment" else dict(os.environ)
    router = open_router(endpoint)
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        while not any('"map store"' in line for line in lines):
            line = proc.stderr.readline()
            assert line, "".join(lines)  # the worker ended before it named its store
            lines.append(line)
        assert SECRET not in open(f"/proc/{proc.pid}/cmdline").read()
    finally:
        proc.terminate()
        rest = proc.communicate(timeout=60)[1]
        router.close()
    logged = "".join(lines) + rest
    assert SECRET not in logged and PASSWORD not in logged and f"postgresql://{user}:***@127.0.0.1" in logged
    url_file.write_text(url.replace(str(pg_cluster.port), str(free_port())) + "\n")
    env[STORE_URL_ENV] = url.replace(str(pg_cluster.port), str(free_port()))
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "unreachable" in out.stderr and f"{user}:***@" in out.stderr, out.stderr
    assert SECRET not in out.stderr and PASSWORD not in out.stderr


def test_libpq_reads_the_password_from_pgpassfile(pg_cluster, tmp_path, monkeypatch):
    """The third way: the URL without a password, the password where libpq looks for it itself."""
    pg_cluster.add_password_user("occvo_passfile", PASSWORD)
    url = f"postgresql://occvo_passfile@127.0.0.1:{pg_cluster.port}/postgres"
    with pytest.raises(StoreUnavailable, match="no password supplied"):
        check_reachable(url)
    passfile = tmp_path / "pgpass"
    passfile.write_text(f"127.0.0.1:{pg_cluster.port}:*:occvo_passfile:{PASSWORD}\n")
    passfile.chmod(0o600)
    monkeypatch.setenv("PGPASSFILE", str(passfile))
    check_reachable(url)
    assert not has_password(url)  # so --store takes it


def test_an_error_line_and_a_run_record_never_hold_the_password(tmp_path):
    import argparse

    from occvo_cli.cli import error_line
    from occvo_cli.run_record import write_run_record
    from occvo_core.config import OccVOConfig

    url = f"postgresql://occvo:{SECRET}@db.lan/occvo"
    assert error_line(RuntimeError(f'invalid dsn: "{url}"')) == (
        'invalid dsn: "postgresql://occvo:***@db.lan/occvo" (RuntimeError; --debug shows the traceback)'
    )
    args = argparse.Namespace(argv=["run", "--note", url], note=url, func=None)
    record = json.loads(write_run_record(tmp_path, args, OccVOConfig()).read_text())
    assert SECRET not in json.dumps(record) and record["options"]["note"] == "postgresql://occvo:***@db.lan/occvo"
    assert record["command"] == "occvo run --note postgresql://occvo:***@db.lan/occvo"


def test_an_unreachable_store_is_named_without_its_password_and_why(pg_cluster, pg_url):
    check_reachable(pg_url)  # reachable: nothing said
    check_reachable("var/occvo.sqlite")  # embedded: nothing to reach
    pg_cluster.add_password_user("occvo_pw", PASSWORD)
    good = f"postgresql://occvo_pw:{SECRET}@127.0.0.1:{pg_cluster.port}/postgres"
    check_reachable(good)
    cases = {
        "wrong password": (good.replace(SECRET, "wrong"), "password authentication failed"),
        "no password": (f"postgresql://occvo_pw@127.0.0.1:{pg_cluster.port}/postgres", "no password supplied"),
        "nothing listening": (good.replace(str(pg_cluster.port), str(free_port())), "refused"),
        "query form": (
            f"postgresql://occvo_pw@127.0.0.1:{free_port()}/postgres?password={SECRET}",
            "refused",
        ),
    }
    for name, (url, why) in cases.items():
        t0 = time.monotonic()
        with pytest.raises(StoreUnavailable) as exc:
            check_reachable(url)
        line = str(exc.value)
        assert time.monotonic() - t0 < 10 and why in line and line.startswith(f"store {redact(url)} unreachable")
        assert SECRET not in line and PASSWORD not in line and "\n" not in line, (name, line)


def test_a_store_opened_with_the_query_form_names_itself_without_the_password(pg_cluster):
    """The pool's label is what every StoreUnavailable (and so every `not_stored` event) says."""
    pg_cluster.add_password_user("occvo_q", PASSWORD)
    url = f"postgresql://occvo_q@127.0.0.1:{pg_cluster.port}/postgres?password={SECRET}"
    store = open_store(url)
    try:
        assert store.streams() == []  # connected: the role's password came from the query
        assert SECRET not in store.label and store.label.endswith("?password=***")
    finally:
        store.close()
    with pytest.raises(StoreUnavailable) as exc:
        open_store(url.replace(str(pg_cluster.port), str(free_port())))
    assert SECRET not in str(exc.value) and "?password=***" in str(exc.value)


def test_a_silent_server_is_given_up_on_within_10_s():
    """A peer that takes the connection and never answers (a hung server, a half-dead host): the start check's
    connect timeout ends it, one line, well before 10 s."""
    import socket

    pytest.importorskip("psycopg", reason="the PostgreSQL driver is not installed (pip install -e '.[postgres]')")

    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)  # the kernel completes the handshake; nothing ever answers
        url = f"postgresql://occvo:{SECRET}@127.0.0.1:{silent.getsockname()[1]}/occvo"
        t0 = time.monotonic()
        with pytest.raises(StoreUnavailable) as exc:
            check_reachable(url)
        took = time.monotonic() - t0
    assert 2 <= took < 10 and "timeout" in str(exc.value) and SECRET not in str(exc.value), (took, str(exc.value))
