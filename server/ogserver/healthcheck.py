"""``python -m ogserver.healthcheck [HOST:PORT] [--tls-ca PEM [--tls-cert PEM --tls-key PEM]]``: exit 0
when the server reports SERVING.

For container health checks, which should not need grpcurl or grpc_health_probe in the image. A
server with TLS needs ``--tls-ca``; one that requires client certificates needs one too.
"""

from __future__ import annotations

import argparse
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
from ogapi import SERVICE_NAME
from ogapi.tls import channel_credentials


def check(address: str, timeout: float = 3.0, credentials: grpc.ChannelCredentials | None = None) -> bool:
    channel = grpc.secure_channel(address, credentials) if credentials else grpc.insecure_channel(address)
    with channel:
        try:
            response = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=SERVICE_NAME), timeout=timeout
            )
        except grpc.RpcError:
            return False
    return response.status == health_pb2.HealthCheckResponse.SERVING


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ogserver.healthcheck", description="Exit 0 when SERVING.")
    parser.add_argument("address", nargs="?", default="127.0.0.1:50051")
    parser.add_argument("--tls-ca", default="", metavar="PEM", help="connect over TLS, trusting this CA")
    parser.add_argument("--tls-cert", default="", metavar="PEM", help="client certificate (mutual TLS)")
    parser.add_argument("--tls-key", default="", metavar="PEM", help="its private key")
    args = parser.parse_args(argv)
    try:
        credentials = channel_credentials(args.tls_ca, args.tls_cert, args.tls_key) if args.tls_ca else None
    except ValueError as error:
        print(f"healthcheck: {error}", file=sys.stderr)
        return 2
    serving = check(args.address, credentials=credentials)
    print(f"{args.address}: {'SERVING' if serving else 'not serving'}")
    return 0 if serving else 1


if __name__ == "__main__":
    sys.exit(main())
