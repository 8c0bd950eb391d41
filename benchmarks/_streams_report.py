"""streams_load.py's report of a run: per bucket of due time, latencies, queues and the slowest poses; over the run,
the backlog's slopes and whether the service keeps up; and its printing."""

from __future__ import annotations

import json
import os
import time

import numpy as np
from _common import pct as _pct
from _common import slope_per_min as _slope
from _common import stage_medians as _stage_medians


def summarise(run: dict) -> dict:
    """The report of a run (_streams_run.run_load's measurements); every pose is also written to log_dir/poses.jsonl."""
    n, rate, minutes, policy, queue_size = (run[k] for k in ("n", "rate", "minutes", "policy", "queue_size"))
    store, bucket_s, log_dir, working_radius = (run[k] for k in ("store", "bucket_s", "log_dir", "working_radius"))
    registration_workers, after_pose_nice = run["registration_workers"], run["after_pose_nice"]
    snapshot_max_share, store_sync, load0 = run["snapshot_max_share"], run["store_sync"], run["load0"]
    streams, samples, t0, send_end = run["streams"], run["samples"], run["t0"], run["send_end"]
    drained, codes, health, reg_health = run["drained"], run["codes"], run["health"], run["reg_health"]
    cpu0, cpu1, io0, io1 = run["cpu0"], run["cpu1"], run["io0"], run["io1"]
    me0, me1, wall0, wall1 = run["me0"], run["me1"], run["wall0"], run["wall1"]

    # ---- per bucket of due time (when a camera would have captured the frame), over all streams
    n_buckets = max(1, int(np.ceil(minutes * 60 / bucket_s)))
    buckets = []
    lat_t, lat_v, cap_v, stages, ids = [], [], [], [], []  # due time - t0, sent_at -> pose, due -> pose, timings_ms
    for st in streams:
        for i in range(st.last_sent + 1):
            if i in st.recv_at:
                ids.append((st.name, i))
                lat_t.append(st.due[i] - t0)
                lat_v.append((st.recv_at[i] - st.sent_at[i]) * 1000.0)
                cap_v.append((st.recv_at[i] - st.due[i]) * 1000.0)
                stages.append(st.timings.get(i, {}))
    lat_t, lat_v, cap_v = np.array(lat_t), np.array(lat_v), np.array(cap_v)
    with open(log_dir / "poses.jsonl", "w") as fp:  # every pose, to lay a burst beside the workers' logs (--log-dir)
        for (name, i), t, lat, timing in zip(ids, lat_t, lat_v, stages):
            fp.write(
                json.dumps(
                    {
                        "stream": name,
                        "seq": i,
                        "due_s": round(float(t), 3),
                        "due_unix": float(t + t0),
                        "latency_ms": round(float(lat), 1),
                        "timings_ms": timing,
                    }
                )
                + "\n"
            )
    smp = np.array(samples) if samples else np.zeros((0, 6))
    for b in range(n_buckets):
        lo, hi = b * bucket_s, (b + 1) * bucket_s
        per = []
        lags = []
        for st in streams:
            due = [i for i in range(len(st.frames)) if lo <= st.due[i] - t0 < hi]
            sent = [i for i in due if st.sent_at[i] == st.sent_at[i]]
            lags += [st.lag[i] for i in sent]
            arrived = sum(1 for t in st.recv_at.values() if lo <= t - t0 < hi)
            per.append(
                {
                    "due": len(due),
                    "sent": len(sent),
                    "received": sum(1 for i in sent if i in st.recv_at),
                    "arrived": arrived,
                }
            )
        in_b = (lat_t >= lo) & (lat_t < hi)
        slow = np.flatnonzero(in_b & (lat_v >= (_pct(lat_v[in_b], 99) or np.inf)))
        # waiting (hops between processes, time in a worker's queue) vs working: a backlog shows in the first
        wait = [sum(v for k, v in stages[j].items() if k.endswith(("_hop", "_queue"))) for j in np.flatnonzero(in_b)]
        sm = smp[(smp[:, 0] >= lo) & (smp[:, 0] < hi)] if len(smp) else smp
        buckets.append(
            {
                "t0_s": lo,
                "due": sum(p["due"] for p in per),
                "sent": sum(p["sent"] for p in per),
                "received": sum(p["received"] for p in per),
                "poses_per_s": sum(p["arrived"] for p in per) / bucket_s,
                "per_stream": {st.name: f"{p['sent']}/{p['received']}" for st, p in zip(streams, per)},
                "latency_p50_ms": _pct(lat_v[in_b], 50),
                "latency_p99_ms": _pct(lat_v[in_b], 99),
                "capture_latency_p50_ms": _pct(cap_v[in_b], 50),
                "capture_latency_p99_ms": _pct(cap_v[in_b], 99),
                "send_lag_max_ms": float(max(lags) * 1000.0) if lags else None,
                "reg_queue_mean": float(sm[:, 1].mean()) if len(sm) else None,
                "reg_queue_max": int(sm[:, 1].max()) if len(sm) else None,
                "in_flight_mean": float(sm[:, 3].mean()) if len(sm) else None,
                "in_flight_max": int(sm[:, 3].max()) if len(sm) else None,
                "slowest_1pct_stage_ms": _stage_medians([stages[j] for j in slow]),
                "wait_p50_ms": _pct(wait, 50),
                "wait_p99_ms": _pct(wait, 99),
                # which poses they were: a burst on one stream (its loop closure) reads differently from one on all
                "slowest_poses": [
                    {
                        "stream": ids[j][0],
                        "seq": ids[j][1],
                        "latency_ms": round(float(lat_v[j]), 1),
                        **{
                            k: round(float(stages[j][k]), 1)
                            for k in ("registration_queue", "registration", "store_commit")
                            if k in stages[j]
                        },
                    }
                    for j in sorted(slow, key=lambda j: -lat_v[j])[:8]
                ],
            }
        )
    sent = sum(st.last_sent + 1 for st in streams)
    received = sum(len([s for s in st.recv_at if s <= st.last_sent]) for st in streams)
    due_total = sum(len(st.frames) for st in streams)
    first, last = buckets[0]["latency_p99_ms"], buckets[-1]["latency_p99_ms"]
    wfirst, wlast = buckets[0]["wait_p99_ms"], buckets[-1]["wait_p99_ms"]
    cfirst, clast = buckets[0]["capture_latency_p99_ms"], buckets[-1]["capture_latency_p99_ms"]
    # sharded: the stage figures below are the busiest shard's
    reg = max(reg_health, key=lambda h: h.counters.get("frames_out", 0), default=None)
    mp = health.get("map")
    build = np.concatenate([st.build_ms for st in streams])
    put = np.concatenate([st.put_ms for st in streams])
    lag = np.concatenate([st.lag for st in streams])
    offered = n * rate
    last_rate = buckets[-1]["poses_per_s"]
    out = {
        "streams": n,
        "rate_hz": rate,
        "minutes": minutes,
        "policy": policy,
        "queue_size": queue_size,
        "store": store,
        "registration_workers": registration_workers,
        "placement": run["placement"],
        "after_pose_nice": after_pose_nice,
        "snapshot_max_share": snapshot_max_share,
        "store_sync": store_sync,
        "working_radius_m": working_radius or None,
        "offered_frames_per_s": offered,
        "due": due_total,
        "sent": sent,
        "received": received,
        "drained": drained,
        "drops": {
            "registration": int(smp[-1, 4]) if len(smp) else 0,
            "inference": int(smp[-1, 5]) if len(smp) else 0,
            "registration_final": sum(h.counters.get("drops", 0) for h in reg_health) if reg_health else None,
        },
        "errors": {st.name: st.errors for st in streams if st.errors},
        "turned_away": sum(st.turned_away for st in streams),  # stream_full: flow control, the frames sent again
        "resends": sum(st.resends for st in streams),
        "p99_ratio_last_first": (last / first) if first and last else None,
        "capture_p99_ratio_last_first": (clast / cfirst) if cfirst and clast else None,
        "wait_p99_ratio_last_first": (wlast / wfirst) if wfirst and wlast else None,
        "slope_capture_latency_ms_per_min": _slope(lat_t, cap_v),
        "slope_reg_queue_per_min": _slope(smp[:, 0], smp[:, 1]) if len(smp) else None,
        "slope_in_flight_per_min": _slope(smp[:, 0], smp[:, 3]) if len(smp) else None,
        "slope_latency_ms_per_min": _slope(lat_t, lat_v),
        "last_bucket_poses_per_s": last_rate,
        "registration_ms_p50": reg.stages["registration"].p50_ms if reg and "registration" in reg.stages else None,
        "registration_stage_mean_ms": reg.stages["stage_total"].mean_ms
        if reg and "stage_total" in reg.stages
        else None,
        "map_update_ms_p50": reg.stages["map_update"].p50_ms if reg and "map_update" in reg.stages else None,
        "worker_cpu_pct": {role: 100.0 * (cpu1[role] - cpu0[role]) / (time.time() - wall0) for role in cpu0},
        "worker_disk_write_mb_per_s": {role: (io1[role] - io0[role]) / 2**20 / (time.time() - wall0) for role in io0},
        "registration_frames_by_worker": sorted((h.counters.get("frames_out", 0) for h in reg_health), reverse=True),
        "registration_counters": {
            k: sum(h.counters.get(k, 0) for h in reg_health)
            for k in ("loop_closures", "after_pose_boosted", "tiles_evicted", "tiles_restored")
        },
        "client_and_router_cpu_pct": 100.0 * (me1 - me0) / (wall1 - wall0),
        "client_build_ms_p50": _pct(build, 50),
        "client_build_ms_p99": _pct(build, 99),
        "client_put_ms_p50": _pct(put, 50),
        "client_put_ms_p99": _pct(put, 99),
        "send_lag_ms_p50": (_pct(lag, 50) or 0) * 1000.0,
        "send_lag_ms_max": float(np.nanmax(lag) * 1000.0) if len(lag) else None,
        "map_apply_ms_p50": mp.stages["apply_update"].p50_ms if mp and "apply_update" in mp.stages else None,
        "map_apply_ms_p99": mp.stages["apply_update"].p99_ms if mp and "apply_update" in mp.stages else None,
        "loadavg_1min_start_end": [load0, os.getloadavg()[0]],
        "worker_exit_codes": codes,
        "buckets": buckets,
        "send_seconds": send_end - t0,
    }
    # keeps up: every frame sent on time and answered, poses come back at the offered rate, frames in flight grow by
    # less than one per stream per minute, and the median latency does not double (p99 of a short bucket is its max)
    c50 = [b["capture_latency_p50_ms"] for b in buckets]
    out["capture_p50_ratio_last_first"] = c50[-1] / c50[0] if c50[0] and c50[-1] else None
    out["keeps_up"] = bool(
        sent == due_total
        and received >= 0.99 * sent
        and drained
        and last_rate >= 0.95 * offered
        and (out["slope_in_flight_per_min"] or 0) <= n
        and (out["capture_p50_ratio_last_first"] or 99) <= 2.0
    )
    return out


def print_run(r: dict, bucket_s: float) -> None:
    print(
        f"\n== {r['streams']} streams x {r['rate_hz']:g} Hz, {r['minutes']:g} min, policy {r['policy']}, "
        f"queue {r['queue_size']}, map store {'sqlite' if r['store'] else 'memory'}, registration "
        + (f"store + eviction at {r['working_radius_m']:g} m" if r["working_radius_m"] else "in memory, no eviction")
        + (
            f", {r['registration_workers']} registration workers ({r.get('placement', 'shards')})"
            if r["registration_workers"] > 1
            else ""
        )
        + (f", a neighbour busy {r['neighbour_load']:g} of every core" if r.get("neighbour_load") else "")
    )
    unit = "min" if bucket_s == 60 else f"{bucket_s:g}s"
    print(
        f"{unit:>5} {'due':>5} {'sent':>5} {'recv':>5} {'poses/s':>7} {'lat p50':>7} {'lat p99':>7} {'cap p50':>7} {'cap p99':>7} "
        f"{'lag max':>7} {'regQ':>5} {'regQmax':>7} {'inflight':>8}  per stream sent/recv"
    )
    fmt = lambda v, f="{:.0f}": "-" if v is None else f.format(v)  # noqa: E731
    for b, x in enumerate(r["buckets"]):
        print(
            f"{b + 1:>5} {x['due']:>5} {x['sent']:>5} {x['received']:>5} {x['poses_per_s']:>7.2f} {fmt(x['latency_p50_ms']):>7} "
            f"{fmt(x['latency_p99_ms']):>7} {fmt(x['capture_latency_p50_ms']):>7} {fmt(x['capture_latency_p99_ms']):>7} "
            f"{fmt(x['send_lag_max_ms']):>7} {fmt(x['reg_queue_mean'], '{:.1f}'):>5} {fmt(x['reg_queue_max']):>7} "
            f"{fmt(x['in_flight_max']):>8}  {' '.join(x['per_stream'].values())}"
        )
    print(
        "waiting (hops + worker queues) p50/p99, and the slowest 1%: median ms of the stages that took most (timings_ms):"
    )
    for b, x in enumerate(r["buckets"]):
        top = list(x.get("slowest_1pct_stage_ms", {}).items())[:6]
        print(
            f"{b + 1:>5}  wait {fmt(x.get('wait_p50_ms'))}/{fmt(x.get('wait_p99_ms'))}  slowest: "
            + ", ".join(f"{k} {v:.0f}" for k, v in top)
        )
    print(
        "(ms; lat = client send -> pose; cap = due time -> pose, what a live camera sees; lag = send - due; regQ = registration "
        "queue depth summed over streams, sampled)"
    )
    print(
        f"due {r['due']} sent {r['sent']} received {r['received']} (offered {r['offered_frames_per_s']:g} frames/s, last bucket "
        f"{r['last_bucket_poses_per_s']:.2f} poses/s), drops reg/inf {r['drops']['registration_final']}/{r['drops']['inference']}, "
        f"drained {r['drained']}"
    )
    print(
        f"backlog: p99 last/first: wait {fmt(r.get('wait_p99_ratio_last_first'), '{:.2f}')}, latency {fmt(r['p99_ratio_last_first'], '{:.2f}')}, capture latency "
        f"{fmt(r['capture_p99_ratio_last_first'], '{:.2f}')} (p50 {fmt(r['capture_p50_ratio_last_first'], '{:.2f}')}); slopes per minute: capture latency "
        f"{fmt(r['slope_capture_latency_ms_per_min'], '{:+.0f}')} ms, registration queue "
        f"{fmt(r['slope_reg_queue_per_min'], '{:+.2f}')}, frames in flight {fmt(r['slope_in_flight_per_min'], '{:+.2f}')}, "
        f"latency {fmt(r['slope_latency_ms_per_min'], '{:+.0f}')} ms  ->  keeps up: {r['keeps_up']}"
    )
    busiest = " (busiest worker)" if r["registration_workers"] > 1 else ""
    print(
        f"registration{busiest} p50 {fmt(r['registration_ms_p50'], '{:.1f}')} ms, stage mean {fmt(r['registration_stage_mean_ms'], '{:.1f}')} ms, "
        f"map tiling p50 {fmt(r['map_update_ms_p50'], '{:.1f}')} ms; map service apply p50/p99 {fmt(r['map_apply_ms_p50'], '{:.1f}')}/"
        f"{fmt(r['map_apply_ms_p99'], '{:.1f}')} ms; load avg start/end {r['loadavg_1min_start_end'][0]:.1f}/"
        f"{r['loadavg_1min_start_end'][1]:.1f}; CPU % "
        f"{json.dumps({k: round(v) for k, v in r['worker_cpu_pct'].items()})}, client+router {r['client_and_router_cpu_pct']:.0f}%"
        + (
            f"; poses a registration worker {r['registration_frames_by_worker']}"
            if r["registration_workers"] > 1
            else ""
        )
    )
    print(
        f"client per frame: build p50 {fmt(r['client_build_ms_p50'], '{:.2f}')} ms p99 {fmt(r['client_build_ms_p99'], '{:.2f}')} ms, "
        f"encode+put p50 {fmt(r['client_put_ms_p50'], '{:.2f}')} ms p99 {fmt(r['client_put_ms_p99'], '{:.2f}')} ms, send lag p50 "
        f"{r['send_lag_ms_p50']:.1f} ms max {fmt(r['send_lag_ms_max'], '{:.0f}')} ms; errors {r['errors'] or 'none'}, "
        f"turned away by a full queue {r['turned_away']} (frames sent again {r['resends']}); "
        f"exit codes {r['worker_exit_codes']}"
    )
    print(
        f"registration counters (all shards): {json.dumps(r['registration_counters'])}; disk writes MB/s "
        f"{json.dumps({k: round(v, 1) for k, v in r['worker_disk_write_mb_per_s'].items()})}"
    )
