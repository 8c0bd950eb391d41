"""Two map-service replicas on one network answer a tile query once: their queryables are complete and the client
queries the best match, so the query goes to one of them (asked of every matching queryable, both answer)."""

from __future__ import annotations

import time

import zenoh

from occvo_schemas import keys
from occvo_services.client import OccVOClient
from occvo_services.commands.replay import load_scene
from occvo_services.local import InProcessService
from occvo_services.map_service import MapService
from occvo_services.runtime import WorkerConfig

NONE = zenoh.ConsolidationMode.NONE  # every reply counted, not one a key


def _last_seq(map_service) -> int | None:
    info = map_service.store.info("rep")
    return None if info is None else info.last_seq


def test_a_tile_query_is_answered_by_one_of_two_map_services():
    scene = load_scene("synthetic:6", frames=3)
    with InProcessService() as svc:
        second = MapService(WorkerConfig(connect=svc.endpoint, worker_id="map-second", log_level="WARNING")).start()
        try:
            with OccVOClient(svc.endpoint, "rep") as c:
                c.reset()
                for i in range(3):
                    c.step(scene[i])
                first = svc.worker("map")
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline and not all(_last_seq(m) == 2 for m in (first, second)):
                    time.sleep(0.05)  # both replicas took the stream's last map update
                assert c.map_info().last_seq == 2
                selector = keys.map_info("rep")
                every, best = (
                    [r for r in c.session.get(selector, target=t, consolidation=NONE, timeout=5) if r.ok]
                    for t in (zenoh.QueryTarget.ALL, zenoh.QueryTarget.BEST_MATCHING)
                )
                assert len(every) == 2 and len(best) == 1  # two replicas; a query for the best match: one answer
        finally:
            second.stop()
