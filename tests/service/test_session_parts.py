"""An object owns its fields: no services module writes another object's fields (the few listed in OWN aside), and
the trajectory view queries read is never changed after it is published."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from occvo_schemas.models import PoseEstimate
from occvo_services.registration.trajectory import StreamTrajectory

SERVICES = Path(__file__).resolve().parents[2] / "services"
# (module, object written) allowed: the pose path fills its frame's FrameJob phase by phase; the OccVO's kernel
# threads are set by its owner (AfterPose); parsed arguments and configs are filled in before anything else holds
# them; the interpreter's and logging's hooks are set at start-up
OWN = {
    ("registration/pose_path.py", "job"),
    ("registration/sequencing.py", "job"),
    ("registration/after_pose.py", "self.vo"),
    ("supervisor.py", "self.router"),
    ("supervisor.py", "cfg"),
    ("supervisor.py", "cfg.router"),
    ("supervisor.py", "w"),
    ("acl.py", "up_config.router"),
    ("acl.py", "w"),
    ("commands/up.py", "config"),
    ("commands/up.py", "config.router"),
    ("commands/up.py", "sup"),
    ("commands/serve.py", "sup"),
    ("telemetry.py", "log"),
    ("worker_cli.py", "sys"),
    ("worker_cli.py", "threading"),
}


def writes_to_others(root: Path, own: set[tuple[str, str]]) -> list[str]:
    """Each `x.field = ...` (or +=, or a for target) where x is not self/cls, not a parsed argparse namespace
    (args) and not in `own`."""
    outside = []
    for path in sorted(root.rglob("*.py")):
        name = path.relative_to(root).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
            for target in filter(None, targets):
                for e in ast.walk(target):
                    if isinstance(e, ast.Attribute) and isinstance(e.ctx, ast.Store):
                        owner = ast.unparse(e.value)
                        if owner not in ("self", "cls", "args") and (name, owner) not in own:
                            outside.append(f"{name}:{e.lineno} {ast.unparse(e)}")
    return outside


def test_no_services_module_writes_another_objects_fields():
    assert writes_to_others(SERVICES, OWN) == []


def test_the_scan_finds_a_write_to_another_objects_field(tmp_path):
    (tmp_path / "eviction.py").write_text("def evict(w, lane):\n    lane.evicting = True\n    w._at += 1\n")
    (tmp_path / "lane.py").write_text("class Lane:\n    def evict(self):\n        self.evicting = True\n")
    assert writes_to_others(tmp_path, set()) == ["eviction.py:2 lane.evicting", "eviction.py:3 w._at"]


def _pose(seq: int, status: str = "ok") -> PoseEstimate:
    return PoseEstimate(stream="s", seq=seq, stamp=0.1 * seq, pose=np.eye(4).tolist(), status=status)


def _m(x: float) -> np.ndarray:
    m = np.eye(4)
    m[0, 3] = x
    return m


def test_a_published_view_stays_as_it_was_published():
    t = StreamTrajectory()
    assert t.view is None and not t.started
    t.record(_pose(0), _m(0.0), b"d0", restart=True)
    first = t.view
    for seq in range(1, 200):  # past the first rows' capacity: the arrays grow
        t.record(_pose(seq), _m(float(seq)), b"d", restart=False)
    assert first.seqs.tolist() == [0] and first.latest.seq == 0 and first.poses[0, 0, 3] == 0.0
    before = t.view
    t.record(_pose(150, "relocalised"), _m(-1.0), b"", restart=False)  # a loop closure replaces seq 150's pose
    assert before.poses[150, 0, 3] == 150.0 and t.view.poses[150, 0, 3] == -1.0
    assert t.stored(150).status == "relocalised" and t.stored(150).digest == b"d" and len(t) == 200
    assert t.view.has(150) and not t.view.has(200) and t.view.last_seq == 199
    t.record(_pose(0), _m(5.0), b"n0", restart=True)  # a new trajectory
    assert before.last_seq == 199 and t.view.seqs.tolist() == [0] and t.stored(199) is None
