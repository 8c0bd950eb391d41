"""PoseEstimate version 1, as clients built before version 2 validate it, and a pose put in that form.

A v1 client decodes with this definition: a status outside its list (`initialised`) or a field it does not know
(`covariance`) fails validation, and its client drops the sample (the pose never arrives). So the registration
worker publishes each pose twice: version 2 on occvo/<stream>/pose/v2 and this form on occvo/<stream>/pose,
where a trajectory's first pose keeps its v1 word `reinitialised` and the covariance is left out.
"""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field, field_validator

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import SEQ_LIMIT, Finite, PoseEstimate, _finite_matrix, _Model, _StreamMessage


class PoseEstimateV1(_StreamMessage):
    model_config = ConfigDict(**_Model.model_config, title="PoseEstimate")  # its JSON Schema as v1 shipped it

    kind: Literal["pose_estimate"] = "pose_estimate"
    schema_version: int = 1
    seq: int = Field(ge=0, lt=SEQ_LIMIT)
    stamp: Finite
    pose: list[list[float]] = Field(description="4x4 ego-to-world, first frame of a trajectory = identity")
    status: Literal["ok", "lost", "reinitialised", "relocalised", "degenerate"]
    timings_ms: dict[str, Finite] = Field(
        default_factory=dict, description="per-stage timings, inference to registration"
    )
    sent_at: Finite = 0.0

    @field_validator("pose")
    @classmethod
    def _p(cls, v):
        return _finite_matrix(v, 4, 4, "pose")


def as_v1(pose: PoseEstimate) -> PoseEstimateV1:
    """The pose as a v1 client reads it: `initialised` said as v1 said it, no covariance."""
    fields = pose.model_dump(exclude={"schema_version", "covariance"})
    if fields["status"] == "initialised":
        fields["status"] = "reinitialised"
    return PoseEstimateV1(**fields)


def pose_puts(pose: PoseEstimate) -> list[tuple[str, bytes]]:
    """(key, payload) of each version a pose is published in: version 2, then version 1."""
    return [(keys.pose(pose.stream), encode(pose)), (keys.pose_v1(pose.stream), encode(as_v1(pose)))]
