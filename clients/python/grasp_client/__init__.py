"""The grasp service's Python client: numpy and httpx only, for a robot's computer.

``GraspClient`` and its sessions (:mod:`grasp_client.client`); what travels on the wire, shared
with the service (:mod:`grasp_client.wire`). The client, and httpx with it, is imported on first
use of one of its names, so that the service and the completion, which share only the wire's
types, do not load it.
"""

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
#: The names :mod:`grasp_client.client` gives, imported when first asked for.
_CLIENT = ("GraspClient", "InvalidRequest", "NothingSeen", "ServiceError", "Session",
           "SessionGone", "Unauthorized", "Unreachable")


def __getattr__(name: str):
    if name in _CLIENT:
        from grasp_client import client

        return getattr(client, name)
    raise AttributeError(f"module 'grasp_client' has no attribute {name!r}")

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
