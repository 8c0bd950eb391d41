"""The client's part of the admission in placement members (services/registration/claims.py), judged before a
frame's placement: a stream bound to the client of its first frame, a client's share of new streams per live member,
an idle stream's claim given to the client's next new stream, claims gone after idle_stream_s."""

from __future__ import annotations

import time

from occvo_services.memory import EVICT_IDLE_S
from occvo_services.registration.claims import Claims


def test_a_stream_is_bound_to_its_client_and_a_client_gets_its_share_on_each_member():
    members = [1]
    claims = Claims(per_client=2, idle_s=30.0, members=lambda: members[0])
    assert claims.claim("a0", "alice") is None and claims.claim("a1", "alice") is None
    code, why = claims.claim("a2", "alice")
    assert code == "stream_limit" and "max_streams_per_client=2" in why and "1 registration workers" in why
    assert claims.claim("a0", "alice") is None  # its own stream's next frame
    code, why = claims.claim("a0", "mallory")
    assert code == "not_owner" and "'a0'" in why
    assert claims.claim("m0", "mallory") is None  # another client's share is its own
    members[0] = 2  # a second member: the client's share doubles
    assert claims.claim("a2", "alice") is None and claims.claim("a3", "alice") is None
    assert claims.claim("a4", "alice")[0] == "stream_limit"


def test_an_idle_stream_gives_its_claim_to_the_clients_next_stream_and_claims_expire():
    claims = Claims(per_client=1, idle_s=EVICT_IDLE_S + 1.0, members=lambda: 1)
    assert claims.claim("a0", "alice") is None
    assert claims.claim("a1", "alice")[0] == "stream_limit"
    time.sleep(EVICT_IDLE_S + 0.1)  # a0 idle: as the owner reclaims its lane, its claim goes to a1
    assert claims.claim("a1", "alice") is None
    assert claims.claim("a0", "alice")[0] == "stream_limit"
    assert claims.claim("a1", "mallory")[0] == "not_owner"
    time.sleep(EVICT_IDLE_S + 1.1)  # a1 idle past idle_s: no longer bound
    assert claims.claim("a1", "mallory") is None
