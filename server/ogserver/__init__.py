"""The OG-Mapping gRPC server: sessions of online mapping behind the ogapi.v1.Mapping service."""

__version__ = "0.1.0"
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"  # the server's and its session actors' logs
