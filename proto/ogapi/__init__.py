"""The OG-Mapping service API: protobuf/gRPC definitions and helpers shared by server and client."""

TOKEN_METADATA_KEY = "x-session-token"
SESSION_METADATA_KEY = "x-session-id"
SERVICE_NAME = "ogapi.v1.Mapping"
