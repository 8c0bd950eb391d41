"""One stream's pose latency with and without a noisy neighbour on the same workers (the service in this process,
real Zenoh sessions): a stream sending at 2 Hz, alone, then beside a stream that sends its frames as fast as the
service answers them (lossless: its full queue answers stream_full and its client sends them again) and a stream
whose client stopped reading its poses.

    python benchmarks/noisy_neighbour.py [--frames 30] [--rate 2]

Prints the steady stream's pose latency p50/p99 alone and with the neighbours, and their ratio (goal: p99 within
1.2x), and whether every pose came, in order, equal between the two runs."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from occvo_schemas import keys  # noqa: E402
from occvo_services.client import OccVOClient  # noqa: E402
from occvo_services.commands.replay import load_scene  # noqa: E402
from occvo_services.local import InProcessService  # noqa: E402
from occvo_services.sessions import open_session  # noqa: E402


def steady(svc, scene, n: int, rate: float, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(latencies ms, poses) of a stream sending n frames at `rate`."""
    lat = []
    with OccVOClient(svc.endpoint, name) as c:
        c.reset()
        t_next = time.perf_counter()
        for i in range(n):
            time.sleep(max(0.0, t_next - time.perf_counter()))
            t0 = time.perf_counter()
            c.wait_pose(c.publish(scene[i]), timeout=120)
            lat.append((time.perf_counter() - t0) * 1000.0)
            t_next += 1.0 / rate
        order = sorted(c.arrived, key=c.arrived.get)
        assert order == list(range(n)) and not c.errors, (order, c.errors)
        return np.array(lat), np.array([c.poses[i].matrix() for i in range(n)])


def noisy(svc, scene, stop: threading.Event, counts: dict) -> None:
    """A stream sending its frames as fast as it is answered, again and again, and one whose client stopped reading
    its poses."""
    reader = open_session(svc.endpoint)
    held = threading.Event()
    sub = reader.declare_subscriber(keys.pose("stalled"), lambda _: held.wait(600))
    try:
        with OccVOClient(svc.endpoint, "burst") as b, OccVOClient(svc.endpoint, "stalled") as s:
            s.reset()
            for f in scene:
                s.publish(f)
            rounds = 0
            while not stop.is_set():
                b.reset()
                for f in scene:
                    b.publish(f)  # waits by itself while frames a full queue turned away go again
                b.wait_pose(len(scene) - 1, timeout=120)
                rounds += 1
            counts.update(burst_rounds=rounds, burst_turned_away=getattr(b, "turned_away", None))
    except Exception as exc:  # noqa: BLE001 - said in the summary
        counts["failed"] = repr(exc)
    finally:
        held.set()
        sub.undeclare()
        reader.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--rate", type=float, default=2.0)
    args = ap.parse_args()
    scene, other = load_scene("synthetic:1", frames=args.frames), load_scene("synthetic:2", frames=12)
    with InProcessService(queue_size=2) as svc:
        steady(svc, scene, 5, args.rate, "warm-up")  # the first frames' kernels and paths
        alone, poses_alone = steady(svc, scene, args.frames, args.rate, "alone")
        stop, counts = threading.Event(), {}
        neighbour = threading.Thread(target=noisy, args=(svc, other, stop, counts))
        neighbour.start()
        time.sleep(1.0)
        beside, poses_beside = steady(svc, scene, args.frames, args.rate, "beside")
        stop.set()
        neighbour.join()
    p50a, p99a = np.percentile(alone, [50, 99])
    p50b, p99b = np.percentile(beside, [50, 99])
    print(f"alone:  p50 {p50a:7.1f} ms  p99 {p99a:7.1f} ms")
    print(f"beside: p50 {p50b:7.1f} ms  p99 {p99b:7.1f} ms  (neighbour: {counts})")
    print(f"p99 ratio {p99b / p99a:.2f} (goal <= 1.2); poses equal: {np.array_equal(poses_alone, poses_beside)}")
    return 1 if "failed" in counts else 0


if __name__ == "__main__":
    sys.exit(main())
