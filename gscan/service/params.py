"""The service's settings (`gscan serve`), apart from the service itself: the command builds them, and a bad
configuration is refused, before the estimator loads."""
from __future__ import annotations

from dataclasses import dataclass, field

from gscan.estimate.params import EstimateParams
from gscan.service.decode import MAX_PIXELS


@dataclass(frozen=True)
class ServeParams:
    max_request_bytes: int = 64 << 20  # a larger request body is refused (413) before it is read
    max_pixels: int = MAX_PIXELS  # per image, checked on the header before decoding
    max_sessions: int = 32  # tracking sessions kept (least recently used dropped first)
    session_ttl_s: float = 600.0  # a session idle this long is dropped
    estimate: EstimateParams = field(default_factory=EstimateParams)  # the estimators' settings (`--config`)
