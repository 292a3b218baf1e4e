"""Who may call and how: session tokens, callers' identities, failed authentications, the limit on
concurrent calls, and the transport (TLS, keepalive)."""
