"""The odometry over a run's frames in the test's own process: what a service run of them must reproduce bit for bit."""


def offline(frames):
    """OccVO after stepping through `frames` from a reset."""
    from occvo_core import OccVO

    vo = OccVO()
    vo.reset()
    for f in frames:
        vo.step(f)
    return vo
