"""The grasp service's Python client: numpy and httpx only, for a robot's computer.

``GraspClient`` and its sessions (:mod:`grasp_client.client`); what travels on the wire, shared
with the service (:mod:`grasp_client.wire`).
"""

from grasp_client.client import (
    GraspClient,
    InvalidRequest,
    NothingSeen,
    ServiceError,
    Session,
    SessionGone,
    Unauthorized,
    Unreachable,
)
from grasp_client.wire import (
    JOINT_NAMES,
    Contact,
    Grasp,
    Primitive,
    SupportPlane,
    Verification,
    WristRise,
)

__version__ = "0.2.0"

__all__ = [
    "JOINT_NAMES",
    "Contact",
    "Grasp",
    "GraspClient",
    "InvalidRequest",
    "NothingSeen",
    "Primitive",
    "ServiceError",
    "Session",
    "SessionGone",
    "SupportPlane",
    "Verification",
    "Unauthorized",
    "Unreachable",
    "WristRise",
]
