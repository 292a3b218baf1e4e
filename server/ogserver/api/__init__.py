"""The ogapi.v1.Mapping service: the servicer, its frame stream, and the translation of requests and
replies between the wire and the engine."""
