"""occvo_core: OCC-VO's algorithms (no transport)."""

from occvo_core.config import OccVOConfig
from occvo_core.errors import ConfigError, DatasetError, InvalidFrameError, OccVOError
from occvo_core.frame import OccupancyFrame
from occvo_core.odometry import OccVO, Registration, StepResult

__all__ = ["OccVO", "OccVOConfig", "Registration", "StepResult", "OccupancyFrame", "OccVOError", "InvalidFrameError", "DatasetError",
           "ConfigError"]
