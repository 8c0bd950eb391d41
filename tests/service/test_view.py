"""The live view (rerun-sdk): a recording of `occvo run --rerun` read back with rerun's own reader, and `occvo view`
following a running service into the web viewer, screenshotted by headless Chromium."""

import http.server
import shutil
import subprocess
import sys
import threading
import time
from collections import Counter

import numpy as np
import pytest

from occvo_core.trajectory import read_kitti, read_tum

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'occvo[view]')")
from rerun.chunk import RrdReader  # noqa: E402 - only where rerun-sdk is installed


def _read(path):
    """Rows per entity path and the chunks' record batches, by rerun's own reader."""
    rows, batches = Counter(), {}
    for chunk in RrdReader(path).stream():
        rows[chunk.entity_path] += chunk.num_rows
        batches.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return rows, batches


def _column(batches, name):
    return [v for b in batches for v in b.column(name).to_pylist()]


def test_occvo_run_rerun_writes_a_recording_rerun_reads_back(tmp_path):
    from occvo_core.sim import SyntheticScene

    out, rrd, n = tmp_path / "out", tmp_path / "out.rrd", 4
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "occvo_cli",
            "run",
            "--frames",
            str(n),
            "--rerun",
            str(rrd),
            "--map-every",
            "2",
            "--out",
            str(out),
            "--quiet",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    rows, batches = _read(rrd)
    assert rows["/world/ego"] == rows["/world/ego/occupancy"] == rows["/world/trajectory"] == n
    assert rows["/world/map"] == 3  # frames 0 and 2, and the final map
    assert rows["/world/moved_objects"] == n - 1  # what left the map with each frame after the first
    scene = SyntheticScene(seed=0, frames=n)
    occupancy = _column(batches["/world/ego/occupancy"], "Points3D:positions")
    assert [len(p) for p in occupancy] == [len(scene[i]) for i in range(n)]
    path = np.array(_column(batches["/world/trajectory"], "LineStrips3D:strips")[-1][0])
    assert np.allclose(path, read_kitti(out / "trajectory.kitti")[:, :3, 3], atol=1e-5)
    final_map = _column(batches["/world/map"], "Points3D:positions")[-1]
    assert len(final_map) == len(np.load(out / "map.npz")["points"])
    stamps = sorted({t for b in batches["/world/ego"] for t in b.column("stamp").cast("int64").to_pylist()})  # ns
    assert np.allclose(np.array(stamps) / 1e9, read_tum(out / "trajectory.tum")[0])


class _SlowPage(http.server.BaseHTTPRequestHandler):
    """A page holding the viewer in a frame and an image that comes after `wait` s: Chromium's screenshot waits for
    the page's load event, and so gives the viewer's WebAssembly that long to start."""

    viewer, wait = "", 30.0

    def do_GET(self):
        if self.path == "/wait":
            time.sleep(self.wait)
            self.send_response(204)
            self.end_headers()
            return
        body = (
            f'<html><body style="margin:0"><iframe src="{self.viewer}" style="border:0;width:100vw;height:100vh">'
            '</iframe><img src="/wait" style="display:none"></body></html>'
        ).encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_chromium() is None, reason="no chromium here (apt-get install chromium; .ci/run installs it)")
def test_occvo_view_follows_the_service_into_the_web_viewer(tmp_path):
    from PIL import Image

    from occvo_core.sim import SyntheticScene
    from occvo_services.client import OccVOClient
    from occvo_services.commands.replay import replay
    from occvo_services.local import InProcessService
    from occvo_services.sessions import free_port

    n, port, rrd = 4, free_port(), tmp_path / "view.rrd"
    with InProcessService() as svc:
        viewer = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occvo_cli",
                "view",
                "--connect",
                svc.endpoint,
                "--stream",
                "car0",
                "--web-port",
                str(port),
                "--rerun",
                str(rrd),
                "--seconds",
                "120",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            url = viewer.stdout.readline().strip().removeprefix("web viewer: ")
            assert url.startswith("http://127.0.0.1:"), viewer.stderr.read()
            with OccVOClient(svc.endpoint, stream="car0") as client:
                client.wait_for_workers(timeout=120)
                sent = replay(client, SyntheticScene(seed=3, frames=n), timeout=300)
            assert sent["poses"] == n
            _SlowPage.viewer = url
            page = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _SlowPage)
            threading.Thread(target=page.serve_forever, daemon=True).start()
            shot = tmp_path / "viewer.png"
            proc = subprocess.run(
                [
                    _chromium(),
                    "--headless=new",
                    "--no-sandbox",
                    "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader",
                    "--window-size=1280,800",
                    f"--screenshot={shot}",
                    f"http://127.0.0.1:{page.server_address[1]}/",
                ],
                check=False,
                capture_output=True,
                timeout=180,
            )
            page.shutdown()
            assert shot.is_file(), proc.stderr.decode()[-2000:]
        finally:
            viewer.terminate()
            summary = viewer.communicate(timeout=60)[0]
    # the viewer rendered (its light panels, not the dark loading screen) and shows the stream: voxels in the
    # class colours of vegetation (0, 175, 0) and driveable surface (255, 0, 255), which its own UI never uses
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    light = (img.min(axis=2) > 200).mean()
    classes = int(((g > 120) & (r < 80) & (b < 80)).sum() + ((r > 200) & (b > 200) & (g < 80)).sum())
    assert light > 0.3 and classes > 1000, (light, classes)
    # what the view got from the service, read back from its recording
    assert '"poses": 4' in summary, summary
    rows, _ = _read(rrd)
    assert rows["/world/ego"] == n and rows["/world/ego/occupancy"] == n
    assert any(p.startswith("/world/map/") for p in rows)


def test_occvo_view_without_a_router_is_one_line_and_leaves_no_recording(tmp_path):
    from occvo_services.sessions import free_port

    rrd = tmp_path / "view.rrd"
    proc = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "view", "--connect", f"tcp/127.0.0.1:{free_port()}", "--rerun", str(rrd)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith("occvo view: error: no router at tcp/127.0.0.1:") and proc.stderr.count("\n") == 1
    assert ".rs" not in proc.stderr and "Error" not in proc.stderr
    assert list(tmp_path.iterdir()) == []
