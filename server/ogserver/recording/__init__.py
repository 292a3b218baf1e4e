"""What a session leaves on disk: its MCAP recording, its checkpoints, and shared storage for a cluster."""
