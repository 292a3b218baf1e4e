"""The session limits' one check, for a single server's registry and the cluster's directory alike."""

from __future__ import annotations

import grpc

from ogserver.errors import ServiceError


def check_room(taken: int, held: int, owner: str, limit: int, quota: int, holder: str) -> None:
    """RESOURCE_EXHAUSTED unless one more session fits: ``taken`` places of ``limit`` are in use (open,
    closing or being built) in the ``holder`` (server or cluster), ``held`` of them by ``owner``."""
    if taken >= limit:
        raise ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED,
                           f"the {holder} already holds its limit of {limit} sessions")
    if quota and held >= quota:
        raise ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED,
                           f"the caller {owner} already holds its limit of {quota} sessions")
