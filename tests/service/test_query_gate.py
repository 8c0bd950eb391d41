"""Whose query budget a query takes (services/query_gate.py): under logins (`client_identity: "user"`) the stream id's
prefix, whatever source info the querier writes; otherwise the source info's session. Real Zenoh sessions on
loopback: a query carrying another session's id (copied) is charged to that id only where ids are the identity."""

from __future__ import annotations

import time

import zenoh

from occvo_services.query_gate import query_client
from occvo_services.sessions import free_port, open_router, zenoh_config


def test_a_copied_source_id_spends_no_other_login_budget():
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    worker, attacker, victim = (zenoh.open(zenoh_config("client", connect=ep)) for _ in range(3))
    charged = []

    def on_query(query):
        charged.append({mode: query_client(str(query.key_expr), query, mode) for mode in ("user", "session")})
        query.reply(query.key_expr, b"ok")

    q = worker.declare_queryable("occvo/**", on_query)
    try:
        time.sleep(0.5)
        copied = zenoh.SourceInfo(victim.id, 7)  # the victim's id, written by the attacker
        list(attacker.get("occvo/mallory.car/map/info", timeout=3.0, source_info=copied))
        list(attacker.get("occvo/mallory.car/map/info", timeout=3.0))
        list(attacker.get("occvo/**", timeout=3.0, source_info=copied))
    finally:
        q.undeclare()
        for s in (worker, attacker, victim, router):
            s.close()
    assert charged[0] == {"user": "mallory", "session": str(victim.id.zid)}
    assert charged[1] == {"user": "mallory", "session": "mallory"}
    assert charged[2] == {"user": "*", "session": "*"}
