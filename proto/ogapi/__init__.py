"""The OG-Mapping service API: protobuf/gRPC definitions and helpers shared by server and client."""

TOKEN_METADATA_KEY = "x-session-token"
SESSION_METADATA_KEY = "x-session-id"
API_KEY_METADATA_KEY = "x-api-key"  # creating, restoring and listing sessions on a server with API keys
SERVICE_NAME = "ogapi.v1.Mapping"
