"""A session's parts own their fields: no registration module writes another object's fields (a frame's own FrameJob
aside), and the trajectory view queries read is never changed after it is published."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from occvo_schemas.models import PoseEstimate
from occvo_services.registration.trajectory import StreamTrajectory

REGISTRATION = Path(__file__).resolve().parents[2] / "services" / "registration"
# (module, object written): the pose path fills its frame's FrameJob phase by phase; the OccVO's kernel threads are
# set by its owner (AfterPose); the worker marks the store it opened as fenced-only
OWN = {("pose_path.py", "job"), ("sequencing.py", "job"), ("after_pose.py", "self.vo"), ("worker.py", "self.store")}


def test_no_registration_module_writes_another_objects_fields():
    outside = []
    for path in sorted(REGISTRATION.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
            for target in filter(None, targets):
                for e in ast.walk(target):
                    if isinstance(e, ast.Attribute) and isinstance(e.ctx, ast.Store):
                        owner = ast.unparse(e.value)
                        if owner not in ("self", "cls") and (path.name, owner) not in OWN:
                            outside.append(f"{path.name}:{e.lineno} {ast.unparse(e)}")
    assert outside == []


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
