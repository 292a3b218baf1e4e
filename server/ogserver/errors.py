"""One exception for every refusal, carrying the gRPC status code the client should see."""

from __future__ import annotations

import grpc


class ServiceError(Exception):
    """A request the server refuses; ``message`` names the offending field."""

    def __init__(self, code: grpc.StatusCode, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message

    def __reduce__(self) -> tuple[type[ServiceError], tuple[grpc.StatusCode, str]]:
        # Refusals cross process boundaries (cluster mode: from a session's Ray actor to its front-end).
        return type(self), (self.code, self.message)


def invalid(field: str, reason: object) -> ServiceError:
    return ServiceError(grpc.StatusCode.INVALID_ARGUMENT, f"{field}: {reason}")


def exhausted(field: str, reason: object) -> ServiceError:
    return ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED, f"{field}: {reason}")
