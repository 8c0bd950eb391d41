"""A live view of a run with rerun-sdk (the optional `view` extra): imported only when a view is asked for.

Entities (world = the odometry's world frame, the first frame's ego):
  world/trajectory          LineStrips3D  the estimated path so far
  world/ego                 Transform3D   the current pose; world/ego/occupancy is the frame's occupancy in the
                                          ego frame, coloured by Occ3D class
  world/moved_objects       Points3D      movable-class map voxels that left the map with this frame: what the
                                          dynamic object filter took out (and the odd one the voxel pfilter let go)
  world/map                 Points3D      the global map (every `map_every` frames and at the end), or
  world/map/<ix>_<iy>       Points3D      one map tile each, as a running service publishes them
  stats/<name>              Scalars       per-frame counters (map voxels, dynamic voxels removed, ...)
Timelines: `frame` (sequence) and `stamp` (the data's clock: a timestamp when it is a real one, else seconds).
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import rerun as rr

from occvo_core.errors import ConfigError
from occvo_core.grid import CLASS_COLORS, MOVABLE_CLASSES, OCC3D_GRID

VIEWER_PORT = 9876  # rerun's native viewer, as rr.spawn starts it
LOOPBACK = "127.0.0.1"  # where the viewers listen unless told (rerun's own default is every interface)
START_TIMEOUT_S = 10.0
REAL_CLOCK_S = 1e8  # stamps past 1973 are wall-clock times; smaller ones are seconds since the scene began
VOXEL_RADIUS = OCC3D_GRID.voxel_size / 2


def _colors(labels: np.ndarray) -> np.ndarray:
    return CLASS_COLORS[np.asarray(labels, np.int64)]


def _keys(points: np.ndarray) -> np.ndarray:
    return np.floor(np.asarray(points) / OCC3D_GRID.voxel_size).astype(np.int64)


class RerunView:
    """Logs a run's steps to one rerun recording (a viewer, a .rrd file, or both)."""

    def __init__(self, recording: rr.RecordingStream, map_every: int = 5, save: Path | None = None):
        self.rec = recording
        self.save = save  # the recording goes to save + ".partial" and is renamed to save by close()
        self.server: subprocess.Popen | None = None  # the web viewer's process, stopped with the view
        self.map_every = max(1, int(map_every))
        self.path: list[np.ndarray] = []
        self._movable: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # keys, points, labels
        self._frames = 0
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    @classmethod
    def open(
        cls,
        app: str = "occvo",
        spawn: bool = False,
        save: str | Path | None = None,
        map_every: int = 5,
        web_port: int | None = None,
        bind: str = LOOPBACK,
    ) -> RerunView:
        """spawn: start a native viewer and stream to it; save: write an .rrd recording; web_port: serve the web
        viewer there (and the data over gRPC on web_port + 1) for a browser (any may be combined). The viewers
        listen on `bind` (loopback unless told, e.g. 0.0.0.0 for every interface)."""
        rec = rr.RecordingStream(app)
        sinks, server = [], None
        if save is not None:
            save = Path(save)
            save.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(_partial(save))))
        if spawn:  # a viewer already on the port is used as it is (as rr.spawn does); a new one outlives the run
            if not _accepting(LOOPBACK, VIEWER_PORT):
                _start_viewer(["--port", str(VIEWER_PORT), "--bind", bind, "--expect-data-soon"], detach=True)
            sinks.append(rr.GrpcSink(f"rerun+http://{_dial(bind)}:{VIEWER_PORT}/proxy"))
        if web_port:  # rerun's web viewer and its data server, a process that ends with this view
            ports = [str(int(web_port) + 1), str(int(web_port))]
            server = _start_viewer(["--serve-web", "--bind", bind, "--port", ports[0], "--web-viewer-port", ports[1]])
            _wait_listening(server, _dial(bind), [int(p) for p in ports])
            sinks.append(rr.GrpcSink(f"rerun+http://{_dial(bind)}:{ports[0]}/proxy"))
        if sinks:  # one set_sinks call
            rec.set_sinks(*sinks)
        view = cls(rec, map_every, save)
        view.server = server
        return view

    def time(self, index: int, stamp: float) -> None:
        self.rec.set_time("frame", sequence=int(index))
        if stamp >= REAL_CLOCK_S:
            self.rec.set_time("stamp", timestamp=float(stamp))
        else:
            self.rec.set_time("stamp", duration=float(stamp))

    def pose(self, index: int, stamp: float, pose: np.ndarray) -> None:
        """The ego pose and the path so far."""
        self.time(index, stamp)
        pose = np.asarray(pose, np.float64)
        self.path.append(pose[:3, 3].copy())
        self.rec.log("world/ego", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        self.rec.log("world/trajectory", rr.LineStrips3D([np.array(self.path)], colors=[[255, 80, 0]]))

    def occupancy(self, points: np.ndarray, labels: np.ndarray) -> None:
        """The current frame's occupancy in the ego frame, coloured by class."""
        self.rec.log("world/ego/occupancy", rr.Points3D(points, colors=_colors(labels), radii=VOXEL_RADIUS))

    def map(self, points: np.ndarray, labels: np.ndarray) -> None:
        self.rec.log("world/map", rr.Points3D(points, colors=_colors(labels), radii=VOXEL_RADIUS * 0.8))

    def clear_map(self) -> None:
        self.rec.log("world/map", rr.Clear(recursive=True))

    def map_tile(self, ix: int, iy: int, points: np.ndarray, labels: np.ndarray) -> None:
        path = f"world/map/{ix}_{iy}"
        if len(points) == 0:
            self.rec.log(path, rr.Clear(recursive=False))
        else:
            self.rec.log(path, rr.Points3D(points, colors=_colors(labels), radii=VOXEL_RADIUS * 0.8))

    def moved_objects(self, points: np.ndarray, labels: np.ndarray) -> None:
        self.rec.log(
            "world/moved_objects",
            rr.Points3D(
                points,
                colors=[[255, 0, 255]] * len(points),
                radii=VOXEL_RADIUS * 1.2,
                class_ids=np.asarray(labels, np.uint16),
            ),
        )

    def scalar(self, name: str, value: float) -> None:
        self.rec.log(f"stats/{name}", rr.Scalars(float(value)))

    def step(self, frame, result, odometry) -> None:
        """One registered frame of OccVO: pose, occupancy, moved objects and, every map_every frames, the map.
        Reads only public results (StepResult, OccVO.map_points)."""
        self.pose(frame.index, frame.stamp, result.pose)
        self.occupancy(frame.points, frame.labels)
        points, labels = odometry.map_points()
        movable = np.isin(labels, MOVABLE_CLASSES)
        keys = _keys(points[movable])
        if self._movable is not None:
            old_keys, old_points, old_labels = self._movable
            gone = ~_rows_in(old_keys, keys)
            self.moved_objects(old_points[gone], old_labels[gone])
            self.scalar("moved_object_voxels", int(gone.sum()))
        self._movable = (keys, points[movable], labels[movable])
        for name in ("dynamic_map_voxels_removed", "dynamic_points", "map_voxels"):
            if name in result.pairs:
                self.scalar(name, result.pairs[name])
        if self._frames % self.map_every == 0:
            self.map(points, labels)
        self._frames += 1

    def finish(self, odometry) -> None:
        """The final map, then flush."""
        self.map(*odometry.map_points())
        self.close()

    def close(self) -> None:
        """Flush and end the recording; a saved one gets its name only now, complete."""
        self.rec.flush()
        self.rec.disconnect()
        self._stop_server()
        if self.save is not None:
            _partial(self.save).replace(self.save)

    def abandon(self) -> None:
        """End the recording after an error or Ctrl-C: a saved one's partial file is removed."""
        self.rec.disconnect()
        self._stop_server()
        if self.save is not None:
            _partial(self.save).unlink(missing_ok=True)

    def _stop_server(self) -> None:
        if self.server is not None and self.server.poll() is None:
            self.server.terminate()
            self.server.wait(10)


def _rerun_binary() -> str:
    """The viewer binary rerun-sdk ships (rerun_cli), else `rerun` on PATH; ConfigError, one line, with neither."""
    try:
        import rerun_cli
    except ImportError:  # a rerun-sdk without the bundled binary: the viewer may be installed on its own
        shipped = None
    else:
        shipped = Path(rerun_cli.__file__).parent / "rerun"
    found = str(shipped) if shipped is not None and shipped.is_file() else shutil.which("rerun")
    if found is None:
        raise ConfigError(
            "no rerun viewer: rerun-sdk ships none here and `rerun` is not on PATH (pip install 'occvo[view]')"
        )
    return found


def _start_viewer(args: list[str], detach: bool = False) -> subprocess.Popen:
    """The rerun binary with `args` (rr.spawn and rr.serve_web_viewer cannot choose the address they listen on)."""
    return subprocess.Popen(
        [_rerun_binary(), *args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=detach,
    )


def _dial(bind: str) -> str:
    """Where this process reaches a server listening on `bind`."""
    return LOOPBACK if bind in ("0.0.0.0", "::", "[::]", "") else bind


def _accepting(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host.strip("[]"), port), timeout=0.2):
            return True
    except OSError:
        return False


def _wait_listening(proc: subprocess.Popen, host: str, ports: list[int]) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not all(_accepting(host, p) for p in ports):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            raise RuntimeError(f"the rerun web viewer did not start on {host} ports {ports} (are they taken?)")
        time.sleep(0.05)


def _partial(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def _rows_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each voxel key (row) of a, whether b holds it; keys packed 21 bits an axis (+-400 km at 0.4 m)."""
    return np.isin(_pack(a), _pack(b))


def _pack(k: np.ndarray) -> np.ndarray:
    k = (np.asarray(k, np.int64) + (1 << 20)) & ((1 << 21) - 1)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]
