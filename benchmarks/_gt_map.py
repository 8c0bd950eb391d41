"""An odometry registered against a map built at the ground-truth poses (along_track.py, coarse_lean.py): what
registration alone adds when nothing before a frame was wrong."""

from __future__ import annotations

from occvo_core import OccVO


class GroundTruthMapOdometry(OccVO):
    """OccVO whose guess is the ground-truth pose and whose map is built at ground-truth poses; the estimate of
    each frame is kept aside in `estimates`."""

    def __init__(self, config, gt):
        self.gt, self.estimates = gt, []
        super().__init__(config)

    def _initial_guess(self, frame):
        return self.gt[len(self._poses)]

    def _commit(self, frame, pose, moved_rows, local=None, *args, **kwargs):
        self.estimates.append(pose)
        super()._commit(frame, self.gt[len(self._poses)], moved_rows, local, *args, **kwargs)
