"""The OG-Mapping gRPC server: sessions of online mapping behind the ogapi.v1.Mapping service."""

__version__ = "0.1.0"
