"""Mapping sessions: each one's map, frame queue and worker, the registry that holds them within the
limits, where they are hosted, and their resumption after a crash."""
